//! Who a dashboard request is from, for the shares of what one client may hold at once
//! (event streams, [`super::streams`]).
//!
//! A request with a session cookie is its session's: every tab of one login is one
//! client, and two logins are two clients even through one SSH tunnel or proxy (where
//! every request comes from 127.0.0.1). A request without one (a bearer header, or an
//! open dashboard) is its source address's, an IPv6 address counted by its /64 as the
//! connection bounds count it (`dray_net::connections::address_key`).

use std::net::IpAddr;

use super::auth::Credential;
use super::auth::sessions::SessionId;

/// One client.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Client {
    /// A login.
    Session(SessionId),
    /// A source address (its key).
    Address(IpAddr),
    /// A request whose connection had no readable peer address (it was already gone).
    Unknown,
}

/// The source address of the connection a request came on (its key), which the
/// dashboard's accept loop puts in each request's extensions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SourceAddress(pub IpAddr);

impl Client {
    /// The client of a request let in with `credential`, from `source`.
    pub fn of(credential: Credential, source: Option<SourceAddress>) -> Client {
        match (credential, source) {
            (Credential::Session(id), _) => Client::Session(id),
            (_, Some(SourceAddress(ip))) => Client::Address(ip),
            (_, None) => Client::Unknown,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_session_is_its_own_client_wherever_it_comes_from() {
        let here = Some(SourceAddress(IpAddr::from([127, 0, 0, 1])));
        let a = Credential::Session(SessionId([1; 16]));
        let b = Credential::Session(SessionId([2; 16]));
        assert_ne!(Client::of(a, here), Client::of(b, here));
        assert_eq!(Client::of(a, here), Client::of(a, None));
        assert_eq!(
            Client::of(Credential::Bearer, here),
            Client::of(Credential::Open, here)
        );
        assert_eq!(Client::of(Credential::Open, None), Client::Unknown);
    }
}
