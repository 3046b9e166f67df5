//! Stand-alone cache hosts (`dray cache`): processes that serve only the CacheService
//! and offer it to the cluster with RegisterCacheHost. While any is registered, jobs
//! place their cache actors on them instead of beside the workers (see
//! [`super::placement`]).
//!
//! There are no heartbeats for cache hosts yet: a registered host stays listed until
//! the coordinator stops. A host that died is found out by the next job that tries to
//! open walls on it, which then leaves it out (and lists it in its `lost_hosts`), so a
//! dead host costs each later job one failed OpenWalls, not its caches.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

use dray_proto::v1::{CacheHost, RegisterCacheHostRequest};
use tonic::Status;

use crate::membership::{VERSION, check_endpoint, check_hostname, version_mismatch};

/// The registered stand-alone cache hosts, in registration order.
#[derive(Debug)]
pub struct CacheHosts {
    hosts: Mutex<Vec<CacheHost>>,
    next: AtomicU64,
}

impl Default for CacheHosts {
    fn default() -> CacheHosts {
        CacheHosts {
            hosts: Mutex::new(Vec::new()),
            next: AtomicU64::new(1),
        }
    }
}

impl CacheHosts {
    fn lock(&self) -> MutexGuard<'_, Vec<CacheHost>> {
        self.hosts.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Check a registration and list the host; returns its id, `cache-N`. The version
    /// must be the coordinator's (FAILED_PRECONDITION otherwise: ray records and
    /// settings are only compatible within one build) and the endpoint a URL
    /// (INVALID_ARGUMENT). A host registering again at an endpoint already listed (it
    /// restarted on the same port) keeps its id and is listed once.
    pub fn register(&self, r: &RegisterCacheHostRequest) -> Result<String, Status> {
        if r.version != VERSION {
            return Err(version_mismatch("cache host", &r.version));
        }
        check_hostname(&r.hostname)?;
        let endpoint = check_endpoint("endpoint", &r.endpoint)?;
        let mut g = self.lock();
        if let Some(h) = g.iter().find(|h| h.endpoint == endpoint) {
            tracing::info!(host = %h.host_id, endpoint = %h.endpoint, "cache host registered again");
            return Ok(h.host_id.clone());
        }
        let id = format!("cache-{}", self.next.fetch_add(1, Ordering::Relaxed));
        tracing::info!(host = %id, %endpoint, hostname = %r.hostname, "cache host registered");
        g.push(CacheHost {
            host_id: id.clone(),
            endpoint,
        });
        Ok(id)
    }

    /// The registered hosts, in registration order.
    pub fn list(&self) -> Vec<CacheHost> {
        self.lock().clone()
    }

    /// Number of registered hosts.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// Whether none is registered.
    pub fn is_empty(&self) -> bool {
        self.lock().is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    fn req(endpoint: &str) -> RegisterCacheHostRequest {
        RegisterCacheHostRequest {
            endpoint: endpoint.into(),
            version: VERSION.into(),
            hostname: "test".into(),
        }
    }

    #[test]
    fn registration_checks_and_ids() {
        let h = CacheHosts::default();
        assert_eq!(h.register(&req("http://10.0.0.1:7100")).unwrap(), "cache-1");
        assert_eq!(
            h.register(&req(" http://10.0.0.2:7100 ")).unwrap(),
            "cache-2"
        );
        // Again at the same endpoint: same id, listed once.
        assert_eq!(h.register(&req("http://10.0.0.1:7100")).unwrap(), "cache-1");
        assert_eq!(h.len(), 2);
        assert_eq!(h.list()[1].endpoint, "http://10.0.0.2:7100");
        let old = RegisterCacheHostRequest {
            version: "0.0.0-other".into(),
            ..req("http://10.0.0.3:7100")
        };
        let e = h.register(&old).unwrap_err();
        assert_eq!(e.code(), Code::FailedPrecondition);
        assert!(e.message().starts_with("version:"), "{}", e.message());
        for bad in ["", "10.0.0.3:7100", "http://", "https:///x"] {
            let e = h.register(&req(bad)).unwrap_err();
            assert_eq!(e.code(), Code::InvalidArgument, "{bad:?}");
            assert!(e.message().starts_with("endpoint:"), "{}", e.message());
        }
        assert_eq!(h.len(), 2);
    }

    /// Issue 20, item 11: no field of a registration comes back whole in an error.
    #[test]
    fn registration_errors_never_echo_an_unbounded_field() {
        let h = CacheHosts::default();
        let huge = "y".repeat(3 << 20);
        let cases = [
            (
                "version",
                RegisterCacheHostRequest {
                    version: huge.clone(),
                    ..req("http://h:1")
                },
            ),
            ("endpoint", req(&huge)),
            ("endpoint", req(&format!("http{huge}"))),
            (
                "hostname",
                RegisterCacheHostRequest {
                    hostname: huge.clone(),
                    ..req("http://h:1")
                },
            ),
        ];
        for (field, r) in cases {
            let e = h.register(&r).unwrap_err();
            assert!(e.message().starts_with(field), "{field}");
            assert!(
                e.message().len() < 400,
                "{field}: {} bytes",
                e.message().len()
            );
        }
        assert!(h.is_empty());
    }
}
