//! What a member (a worker, a stand-alone cache host) must present to register: the
//! coordinator's own build, a bounded host name, an endpoint peers can reach. A leaf
//! that [`crate::membership`] (workers) and [`crate::caches::hosts`] (cache hosts) both
//! check against, so neither depends on the other for it.

use tonic::Status;

/// The dray version every worker must have been built from: rays, packages and settings
/// are only guaranteed bit-compatible within one build of the workspace.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The longest endpoint URL a member may announce (a host name is at most 253 bytes).
pub const MAX_ENDPOINT_BYTES: usize = 1024;
/// The longest host name a member may announce (it is only logged).
pub const MAX_HOSTNAME_BYTES: usize = 256;

/// `version` as a member announced it, for an error: cut (it is input).
pub fn version_mismatch(what: &str, version: &str) -> Status {
    Status::failed_precondition(format!(
        "version: the {what} is dray {} but the coordinator is dray {VERSION:?}; \
         rays are only compatible within one build, so run the same dray everywhere",
        crate::text::bounded(version)
    ))
}

/// Check the host name a member announced: at most [`MAX_HOSTNAME_BYTES`].
pub fn check_hostname(hostname: &str) -> Result<(), Status> {
    if hostname.len() > MAX_HOSTNAME_BYTES {
        return Err(Status::invalid_argument(format!(
            "hostname: {} bytes is longer than {MAX_HOSTNAME_BYTES}",
            hostname.len()
        )));
    }
    Ok(())
}

/// Check an endpoint a peer announced (`field` names it in the error): an http(s) URL
/// with a host, such as `http://10.0.0.7:7001`. Returns it trimmed. INVALID_ARGUMENT
/// otherwise: the caller must fix its flags, retrying cannot help.
pub fn check_endpoint(field: &str, raw: &str) -> Result<String, Status> {
    if raw.len() > MAX_ENDPOINT_BYTES {
        return Err(Status::invalid_argument(format!(
            "{field}: {} bytes is longer than {MAX_ENDPOINT_BYTES}",
            raw.len()
        )));
    }
    let endpoint = raw.trim();
    let host = endpoint
        .strip_prefix("http://")
        .or_else(|| endpoint.strip_prefix("https://"));
    if host.is_none_or(|h| h.is_empty() || h.starts_with('/')) {
        return Err(Status::invalid_argument(format!(
            "{field}: {} is not a URL such as http://10.0.0.7:7001 that peers can reach",
            crate::text::bounded(raw)
        )));
    }
    Ok(endpoint.to_string())
}
