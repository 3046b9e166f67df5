//! Stand-alone cache hosts (`dray cache`): processes that serve only the CacheService
//! and offer it to the cluster with RegisterCacheHost; while any is registered, jobs
//! place their cache actors on them instead of beside the workers (see
//! [`super::placement`]).
//!
//! A host answers every lookup of the walls it holds, so it can change any image: a
//! coordinator takes stand-alone hosts only when its operator says so (`--cache-hosts`,
//! checked by the RegisterCacheHost handler), and each host gets a secret of its own at
//! its first registration. It calls again every heartbeat interval with that secret to
//! stay listed (no one else can take over its endpoint); one silent for the heartbeat
//! timeout is dropped by the coordinator's reaper, so dead hosts do not pile up. A host
//! that died between two refreshes is found out by the next job that tries to open walls
//! on it, which then leaves it out (and lists it in its `lost_hosts`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use dray_proto::v1::{CacheHost, RegisterCacheHostRequest};
use tonic::Status;

use crate::registration::{VERSION, check_endpoint, check_hostname, version_mismatch};

/// The most stand-alone hosts listed at once (each is a placement candidate for every
/// job): a member flooding registrations cannot grow the list without bound.
pub const MAX_CACHE_HOSTS: usize = 1024;

/// A listed host, its secret and when it was last heard from.
#[derive(Debug)]
struct Entry {
    host: CacheHost,
    token: dray_net::Token,
    last_seen: Instant,
}

/// The registered stand-alone cache hosts, in registration order.
#[derive(Debug)]
pub struct CacheHosts {
    hosts: Mutex<Vec<Entry>>,
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

/// What a registration gives the host: its id and secret.
#[derive(Debug)]
pub struct Registered {
    pub host_id: String,
    pub member_token: String,
}

impl CacheHosts {
    fn lock(&self) -> MutexGuard<'_, Vec<Entry>> {
        dray_sync::lock(&self.hosts)
    }

    /// Check a registration and list the host (or refresh it); returns its id, `cache-N`,
    /// and its secret. The version must be the coordinator's (FAILED_PRECONDITION
    /// otherwise: ray records and settings are only compatible within one build) and
    /// the endpoint a URL (INVALID_ARGUMENT). A call for an endpoint already listed must
    /// carry that host's secret (PERMISSION_DENIED otherwise) and refreshes it, keeping
    /// its id; a host whose listing expired (or a coordinator that restarted) lists it
    /// anew.
    pub fn register(&self, r: &RegisterCacheHostRequest) -> Result<Registered, Status> {
        if r.version != VERSION {
            return Err(version_mismatch("cache host", &r.version));
        }
        check_hostname(&r.hostname)?;
        let endpoint = check_endpoint("endpoint", &r.endpoint)?;
        let mut g = self.lock();
        if let Some(h) = g.iter_mut().find(|h| h.host.endpoint == endpoint) {
            if !h.token.matches(r.member_token.as_bytes()) {
                return Err(Status::permission_denied(format!(
                    "endpoint: {} is already registered as {}, and this call does not \
                     carry its member secret",
                    crate::text::bounded(&endpoint),
                    h.host.host_id
                )));
            }
            h.last_seen = Instant::now();
            tracing::debug!(host = %h.host.host_id, endpoint = %h.host.endpoint, "cache host refreshed");
            return Ok(Registered {
                host_id: h.host.host_id.clone(),
                member_token: h.token.expose().to_string(),
            });
        }
        if g.len() >= MAX_CACHE_HOSTS {
            return Err(Status::resource_exhausted(format!(
                "the coordinator lists {MAX_CACHE_HOSTS} cache hosts, its limit"
            )));
        }
        let token = dray_net::Token::generate()
            .map_err(|e| Status::internal(format!("cannot make a member token: {e}")))?;
        let id = format!("cache-{}", self.next.fetch_add(1, Ordering::Relaxed));
        tracing::info!(host = %id, %endpoint, hostname = %r.hostname, "cache host registered");
        let member_token = token.expose().to_string();
        g.push(Entry {
            host: CacheHost {
                host_id: id.clone(),
                endpoint,
            },
            token,
            last_seen: Instant::now(),
        });
        Ok(Registered {
            host_id: id,
            member_token,
        })
    }

    /// Drop the hosts not heard from for `timeout` before `now`; returns them.
    pub fn expire(&self, now: Instant, timeout: Duration) -> Vec<CacheHost> {
        let mut g = self.lock();
        let mut lost = Vec::new();
        g.retain(|h| {
            let silent = now.saturating_duration_since(h.last_seen);
            if silent > timeout {
                tracing::warn!(host = %h.host.host_id, endpoint = %h.host.endpoint, ?silent, "cache host lost: no refresh");
                lost.push(h.host.clone());
                false
            } else {
                true
            }
        });
        lost
    }

    /// The registered hosts, in registration order.
    pub fn list(&self) -> Vec<CacheHost> {
        self.lock().iter().map(|h| h.host.clone()).collect()
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
            member_token: String::new(),
        }
    }

    #[test]
    fn registration_checks_and_ids() {
        let h = CacheHosts::default();
        let first = h.register(&req("http://10.0.0.1:7100")).unwrap();
        assert_eq!(first.host_id, "cache-1");
        assert_eq!(
            h.register(&req(" http://10.0.0.2:7100 ")).unwrap().host_id,
            "cache-2"
        );
        // Again at the same endpoint, with its secret: same id, listed once.
        let again = RegisterCacheHostRequest {
            member_token: first.member_token.clone(),
            ..req("http://10.0.0.1:7100")
        };
        assert_eq!(h.register(&again).unwrap().host_id, "cache-1");
        // Without it, or with another host's: refused (docs/security.md "Hardening, second
        // round", item 6).
        let e = h.register(&req("http://10.0.0.1:7100")).unwrap_err();
        assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
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

    /// docs/security.md "Hardening, second round", item 11: no field of a registration
    /// comes back whole in an error.
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

    /// docs/security.md "Hardening, second round", item 15: registered hosts were never
    /// expired (3,000 dead ones stayed).
    #[test]
    fn silent_hosts_expire_and_refreshed_ones_stay() {
        let h = CacheHosts::default();
        let a = h.register(&req("http://10.0.0.1:7100")).unwrap();
        h.register(&req("http://10.0.0.2:7100")).unwrap();
        let timeout = Duration::from_secs(5);
        assert!(h.expire(Instant::now(), timeout).is_empty());
        // a refreshes; 6 s later only b has been silent for longer than the timeout.
        let later = Instant::now() + Duration::from_secs(6);
        h.lock()[0].last_seen = later;
        let lost = h.expire(later, timeout);
        assert_eq!(lost.len(), 1);
        assert_eq!(lost[0].endpoint, "http://10.0.0.2:7100");
        assert_eq!(h.list()[0].host_id, a.host_id);
        // A dropped host registering again is listed anew, with a new id.
        assert_eq!(
            h.register(&req("http://10.0.0.2:7100")).unwrap().host_id,
            "cache-3"
        );
    }
}
