//! Who may use the dashboard, and which requests may change anything.
//!
//! - **The API token** (`--auth-token-file`), when the coordinator has one, is required
//!   on every `/api/` endpoint, as the gRPC API requires it on RenderService: either as
//!   `Authorization: Bearer TOKEN` (scripts) or as the session cookie that `POST
//!   /api/login` sets once the token was typed into the page. The cookie holds no token:
//!   it is an expiry time and a random session id, signed with a key made when the
//!   process started (HMAC-SHA256), so it is useless once the coordinator restarts or
//!   the time passes; and the id must be one of the live sessions ([`sessions`]), so
//!   `POST /api/logout` ends it for every copy of the cookie, not only the browser's.
//!   It is `HttpOnly` (scripts on the page cannot read it) and `SameSite=Strict` (a
//!   request another site makes the browser send does not carry it).
//! - **Cross-site requests**: a request that changes anything (any method but GET and
//!   HEAD) must carry the header `X-Dray-Csrf: 1`, which a form or a link on another
//!   site cannot add and a cross-origin script may add only after a CORS preflight this
//!   server never grants; and its `Origin`, when the browser sends one, must be this
//!   server's own host. A request authenticated by a bearer header is exempt: a browser
//!   never adds that header on its own.
//! - **Without a token** the dashboard is as open as the gRPC API, but it answers only
//!   requests whose `Host` is an IP address or `localhost`: a page on another site whose
//!   name is made to resolve to this machine (DNS rebinding) would otherwise be same-origin
//!   with it. With a token that is moot (the attacker's origin has no session).

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use axum::http::{HeaderMap, Method, header};
use dray_net::Token;
use ring::hmac;

pub mod sessions;

use sessions::{SessionId, Sessions};

/// The session cookie's name.
pub const SESSION_COOKIE: &str = "dray_session";
/// The header a state-changing request must carry (any value but empty).
pub const CSRF_HEADER: &str = "x-dray-csrf";
/// How long a login lasts.
pub const SESSION_LIFETIME: Duration = Duration::from_secs(12 * 3600);

/// How a request was let in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Credential {
    /// The coordinator has no API token.
    Open,
    /// `Authorization: Bearer` with the API token.
    Bearer,
    /// A valid session cookie of this live session.
    Session(SessionId),
}

/// Why a request is refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Denied {
    /// No credential, or a wrong one: 401, and the page shows its login.
    Unauthenticated(String),
    /// A cross-site request, or a host name an open dashboard does not answer: 403.
    Forbidden(String),
    /// The server cannot make a session now (no random numbers): 503.
    Unavailable(String),
}

/// The dashboard's credentials: the API token, if any, and the key sessions are
/// signed with.
pub struct Gate {
    token: Option<Token>,
    key: hmac::Key,
    sessions: Sessions,
}

impl Gate {
    /// A gate for `token` (none: the dashboard is open), with a new random session key.
    pub fn new(token: Option<Token>) -> Result<Gate, ring::error::Unspecified> {
        let key = hmac::Key::generate(hmac::HMAC_SHA256, &ring::rand::SystemRandom::new())?;
        Ok(Gate {
            token,
            key,
            sessions: Sessions::default(),
        })
    }

    /// A gate whose session key is `key` (tests).
    pub fn with_key(token: Option<Token>, key: &[u8]) -> Gate {
        Gate {
            token,
            key: hmac::Key::new(hmac::HMAC_SHA256, key),
            sessions: Sessions::default(),
        }
    }

    /// Whether the API token is required.
    pub fn requires_token(&self) -> bool {
        self.token.is_some()
    }

    /// The credential `headers` present, at time `now`.
    pub fn authenticate(&self, headers: &HeaderMap, now: SystemTime) -> Result<Credential, Denied> {
        let Some(token) = &self.token else {
            return open_host(headers).map(|()| Credential::Open);
        };
        if let Some(auth) = headers.get(header::AUTHORIZATION) {
            let presented = auth
                .as_bytes()
                .strip_prefix(b"Bearer ")
                .or_else(|| auth.as_bytes().strip_prefix(b"bearer "));
            return match presented {
                Some(p) if token.matches(p) => Ok(Credential::Bearer),
                _ => Err(Denied::Unauthenticated(
                    "the bearer token presented is not the API token".into(),
                )),
            };
        }
        match cookie(headers, SESSION_COOKIE) {
            Some(v) => match self.live_session(v, now) {
                Some(id) => Ok(Credential::Session(id)),
                None => Err(Denied::Unauthenticated(
                    "the session has expired, was logged out or is from an earlier \
                     coordinator: log in again"
                        .into(),
                )),
            },
            None => Err(Denied::Unauthenticated(
                "this dashboard needs the API token: log in, or send \"Authorization: Bearer \
                 TOKEN\""
                    .into(),
            )),
        }
    }

    /// Whether a request with `method` and `headers`, let in by `credential`, may change
    /// anything (see the module's doc).
    pub fn check_csrf(
        method: &Method,
        headers: &HeaderMap,
        credential: Credential,
    ) -> Result<(), Denied> {
        if matches!(*method, Method::GET | Method::HEAD) || credential == Credential::Bearer {
            return Ok(());
        }
        if headers.get(CSRF_HEADER).is_none_or(|v| v.is_empty()) {
            return Err(Denied::Forbidden(format!(
                "a request that changes anything must carry the header {CSRF_HEADER}"
            )));
        }
        if let Some(origin) = headers.get(header::ORIGIN) {
            let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
            // The scheme must be one a browser loads this page over: plain HTTP, or
            // HTTPS through a TLS proxy in front of it. Any other (`file://`, a custom
            // scheme of an app) is another origin even with this host (issue 45, item 12).
            let origin_host = origin
                .to_str()
                .ok()
                .and_then(|o| o.split_once("://"))
                .filter(|(scheme, _)| {
                    scheme.eq_ignore_ascii_case("http") || scheme.eq_ignore_ascii_case("https")
                })
                .map(|(_, rest)| rest);
            match (origin_host, host) {
                (Some(o), Some(h)) if o.eq_ignore_ascii_case(h) => {}
                _ => {
                    return Err(Denied::Forbidden(
                        "a cross-origin request may not change anything here".into(),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Log in with the token `presented`: the `Set-Cookie` value of a new session.
    pub fn login(&self, presented: &str, now: SystemTime) -> Result<String, Denied> {
        let Some(token) = &self.token else {
            return Err(Denied::Forbidden(
                "this coordinator has no API token: there is nothing to log in to".into(),
            ));
        };
        if !token.matches(presented.trim().as_bytes()) {
            return Err(Denied::Unauthenticated("that is not the API token".into()));
        }
        let id = SessionId::generate()
            .map_err(|_| Denied::Unavailable("cannot make a session id: try again".into()))?;
        let now = unix_seconds(now);
        let expires = now.saturating_add(SESSION_LIFETIME.as_secs());
        self.sessions.start(id, expires, now);
        Ok(format!(
            "{SESSION_COOKIE}={}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}",
            self.session_value(expires, &id),
            SESSION_LIFETIME.as_secs()
        ))
    }

    /// Log out: the session of the cookie in `headers`, if it carries a genuine one,
    /// ends (every copy of the cookie is refused from now on). The `Set-Cookie` value
    /// that clears the browser's cookie.
    pub fn logout(&self, headers: &HeaderMap) -> String {
        if let Some((id, _)) = cookie(headers, SESSION_COOKIE).and_then(|v| self.signed(v)) {
            self.sessions.end(&id);
        }
        format!("{SESSION_COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0")
    }

    /// Whether session `id` is still live at `now` (not logged out, not expired, not pushed out
    /// by newer logins): an event stream it opened ends when it is not.
    pub fn session_live(&self, id: &SessionId, now: SystemTime) -> bool {
        self.sessions.contains(id, unix_seconds(now))
    }

    /// `EXPIRES.ID.MAC`: the expiry in Unix seconds, the session id and their HMAC, hex.
    fn session_value(&self, expires: u64, id: &SessionId) -> String {
        let signed = format!("{expires}.{}", id.hex());
        let tag = hmac::sign(&self.key, signed.as_bytes());
        format!("{signed}.{}", hex(tag.as_ref()))
    }

    /// The session id and expiry of a cookie value signed with this gate's key.
    fn signed(&self, value: &str) -> Option<(SessionId, u64)> {
        let (signed, mac) = value.rsplit_once('.')?;
        let (expires, id) = signed.split_once('.')?;
        let (exp, id, mac) = (
            expires.parse::<u64>().ok()?,
            SessionId::parse(id)?,
            unhex(mac)?,
        );
        hmac::verify(&self.key, signed.as_bytes(), &mac).ok()?;
        Some((id, exp))
    }

    /// The session of a cookie value that is genuine, unexpired at `now` and live.
    fn live_session(&self, value: &str, now: SystemTime) -> Option<SessionId> {
        let (id, exp) = self.signed(value)?;
        self.sessions
            .live(&id, exp, unix_seconds(now))
            .then_some(id)
    }
}

/// An open dashboard answers only a `Host` that is an IP address or `localhost`.
fn open_host(headers: &HeaderMap) -> Result<(), Denied> {
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .unwrap_or("");
    let name = match host.strip_prefix('[') {
        Some(v6) => v6.split(']').next().unwrap_or(""),
        None => host.rsplit_once(':').map_or(host, |(n, _)| n),
    };
    let name = name.to_ascii_lowercase();
    if name.parse::<std::net::IpAddr>().is_ok()
        || name == "localhost"
        || name.ends_with(".localhost")
    {
        return Ok(());
    }
    Err(Denied::Forbidden(format!(
        "this dashboard has no API token, so it answers only requests to an IP address or \
         localhost, not {:?} (start the coordinator with --auth-token-file to serve it under \
         a name)",
        name.chars().take(64).collect::<String>()
    )))
}

/// The value of cookie `name` in `headers`' `Cookie` lines.
fn cookie<'a>(headers: &'a HeaderMap, name: &str) -> Option<&'a str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|line| line.split(';'))
        .filter_map(|pair| pair.trim().split_once('='))
        .find(|(k, _)| *k == name)
        .map(|(_, v)| v)
}

fn unix_seconds(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) || s.len() > 128 {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok())
        .collect()
}

#[cfg(test)]
mod tests;
