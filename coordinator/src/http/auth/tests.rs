//! The dashboard's credentials and cross-site checks, header by header.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use axum::http::{HeaderMap, HeaderValue, Method, header};

use super::*;

const TOKEN: &str = "0123456789abcdef-api";
/// A session credential, for the cross-site checks (which look only at its kind).
const SESSION: Credential = Credential::Session(sessions::SessionId([7; 16]));

fn gate() -> Gate {
    Gate::with_key(Some(Token::parse(TOKEN, "test").unwrap()), b"session key")
}

fn at(secs: u64) -> SystemTime {
    UNIX_EPOCH + Duration::from_secs(secs)
}

fn headers(pairs: &[(header::HeaderName, &str)]) -> HeaderMap {
    let mut h = HeaderMap::new();
    for (k, v) in pairs {
        h.append(k.clone(), HeaderValue::from_str(v).unwrap());
    }
    h
}

/// The cookie's `name=value` from a `Set-Cookie` line.
fn cookie_pair(set_cookie: &str) -> String {
    set_cookie.split(';').next().unwrap().to_string()
}

#[test]
fn the_bearer_header_lets_in_only_the_api_token() {
    let g = gate();
    let ok = headers(&[(header::AUTHORIZATION, &format!("Bearer {TOKEN}"))]);
    assert_eq!(g.authenticate(&ok, at(1000)), Ok(Credential::Bearer));
    for wrong in [
        format!("Bearer {TOKEN}x"),
        "Bearer 0123456789abcdef-apj".to_string(),
        TOKEN.to_string(),
        "Basic abc".to_string(),
    ] {
        let h = headers(&[(header::AUTHORIZATION, &wrong)]);
        assert!(
            matches!(
                g.authenticate(&h, at(1000)),
                Err(Denied::Unauthenticated(_))
            ),
            "{wrong}"
        );
    }
    assert!(matches!(
        g.authenticate(&HeaderMap::new(), at(1000)),
        Err(Denied::Unauthenticated(_))
    ));
}

#[test]
fn login_sets_an_httponly_strict_cookie_that_lets_in_until_it_expires() {
    let g = gate();
    assert!(matches!(
        g.login("not the token at all", at(1000)),
        Err(Denied::Unauthenticated(_))
    ));
    let set = g.login(&format!("{TOKEN}\n"), at(1000)).unwrap();
    for attr in ["HttpOnly", "SameSite=Strict", "Path=/", "Max-Age=43200"] {
        assert!(set.contains(attr), "{set}");
    }
    assert!(
        !set.contains(TOKEN),
        "the cookie must not carry the token: {set}"
    );
    let h = headers(&[(
        header::COOKIE,
        &format!("theme=dark; {}", cookie_pair(&set)),
    )]);
    assert!(matches!(
        g.authenticate(&h, at(1000)),
        Ok(Credential::Session(_))
    ));
    let end = 1000 + SESSION_LIFETIME.as_secs();
    assert!(matches!(
        g.authenticate(&h, at(end - 1)),
        Ok(Credential::Session(_))
    ));
    assert!(matches!(
        g.authenticate(&h, at(end)),
        Err(Denied::Unauthenticated(_))
    ));
}

/// Issue 45, item 12: sessions were an expiry signed with the process's key, so a
/// cookie copied before logout still worked after it. Logout now ends the session for
/// every copy; another session goes on.
#[test]
fn a_cookie_used_after_logout_is_refused() {
    let g = gate();
    let cookie_of = |set: &str| headers(&[(header::COOKIE, &cookie_pair(set))]);
    let mine = cookie_of(&g.login(TOKEN, at(1000)).unwrap());
    let other = cookie_of(&g.login(TOKEN, at(1000)).unwrap());
    let Ok(Credential::Session(a)) = g.authenticate(&mine, at(1001)) else {
        panic!("a fresh session lets in");
    };
    let Ok(Credential::Session(b)) = g.authenticate(&other, at(1001)) else {
        panic!("a fresh session lets in");
    };
    assert_ne!(a, b, "each login is its own session");
    let cleared = g.logout(&mine);
    assert!(cleared.contains("Max-Age=0"), "{cleared}");
    // The copy kept from before logout: refused, now and later.
    for t in [1002, 2000] {
        assert!(
            matches!(
                g.authenticate(&mine, at(t)),
                Err(Denied::Unauthenticated(_))
            ),
            "at {t}"
        );
    }
    assert!(!g.session_live(&a, at(1002)));
    assert_eq!(g.authenticate(&other, at(1002)), Ok(Credential::Session(b)));
    // Logging out with no cookie, or a forged one, ends nothing.
    g.logout(&HeaderMap::new());
    g.logout(&headers(&[(
        header::COOKIE,
        &format!("{SESSION_COOKIE}=1.2.3"),
    )]));
    assert!(g.session_live(&b, at(1002)));
}

#[test]
fn a_forged_or_foreign_session_is_refused() {
    let g = gate();
    let set = g.login(TOKEN, at(1000)).unwrap();
    let pair = cookie_pair(&set);
    let value = pair.split_once('=').unwrap().1;
    let (exp, mac) = value.split_once('.').unwrap();
    // A later expiry with the old signature; a signature from another key (a restarted
    // coordinator); garbage.
    let later = format!("{}.{mac}", exp.parse::<u64>().unwrap() + 3600);
    let other = Gate::with_key(Some(Token::parse(TOKEN, "t").unwrap()), b"another key")
        .login(TOKEN, at(1000))
        .unwrap();
    let other = cookie_pair(&other).split_once('=').unwrap().1.to_string();
    for bad in [
        later,
        other,
        "123".into(),
        "x.y".into(),
        format!("{exp}.zz"),
    ] {
        let h = headers(&[(header::COOKIE, &format!("{SESSION_COOKIE}={bad}"))]);
        assert!(
            matches!(
                g.authenticate(&h, at(1000)),
                Err(Denied::Unauthenticated(_))
            ),
            "{bad}"
        );
    }
}

#[test]
fn state_changing_requests_need_the_csrf_header_and_their_own_origin() {
    let host = (header::HOST, "127.0.0.1:8080");
    let csrf = (header::HeaderName::from_static(CSRF_HEADER), "1");
    let post = Method::POST;
    // Reads need nothing.
    assert_eq!(
        Gate::check_csrf(&Method::GET, &headers(std::slice::from_ref(&host)), SESSION),
        Ok(())
    );
    // A cookie or an open dashboard: the header is required.
    for c in [SESSION, Credential::Open] {
        assert!(matches!(
            Gate::check_csrf(&post, &headers(std::slice::from_ref(&host)), c),
            Err(Denied::Forbidden(_))
        ));
        assert_eq!(
            Gate::check_csrf(&post, &headers(&[host.clone(), csrf.clone()]), c),
            Ok(())
        );
    }
    // With it, an Origin must be this host.
    let same = (header::ORIGIN, "http://127.0.0.1:8080");
    let evil = (header::ORIGIN, "https://evil.example");
    let null = (header::ORIGIN, "null");
    let other_scheme = (header::ORIGIN, "file://127.0.0.1:8080");
    let app_scheme = (header::ORIGIN, "chrome-extension://127.0.0.1:8080");
    let tls_proxy = (header::ORIGIN, "https://127.0.0.1:8080");
    assert_eq!(
        Gate::check_csrf(
            &post,
            &headers(&[host.clone(), csrf.clone(), tls_proxy]),
            SESSION
        ),
        Ok(())
    );
    assert_eq!(
        Gate::check_csrf(
            &post,
            &headers(&[host.clone(), csrf.clone(), same]),
            SESSION
        ),
        Ok(())
    );
    for o in [evil, null, other_scheme, app_scheme] {
        assert!(matches!(
            Gate::check_csrf(&post, &headers(&[host.clone(), csrf.clone(), o]), SESSION),
            Err(Denied::Forbidden(_))
        ));
    }
    // A bearer header is never sent by a browser on its own: exempt.
    assert_eq!(
        Gate::check_csrf(&post, &headers(&[host]), Credential::Bearer),
        Ok(())
    );
}

#[test]
fn an_open_dashboard_answers_ip_addresses_and_localhost_only() {
    let g = Gate::with_key(None, b"k");
    assert!(!g.requires_token());
    for ok in [
        "127.0.0.1:8080",
        "10.1.2.3",
        "[::1]:80",
        "localhost:8080",
        "a.localhost",
    ] {
        let h = headers(&[(header::HOST, ok)]);
        assert_eq!(g.authenticate(&h, at(0)), Ok(Credential::Open), "{ok}");
    }
    for bad in ["evil.example:8080", "rebind.attacker.test", ""] {
        let h = headers(&[(header::HOST, bad)]);
        assert!(
            matches!(g.authenticate(&h, at(0)), Err(Denied::Forbidden(_))),
            "{bad}"
        );
    }
    assert!(matches!(g.login(TOKEN, at(0)), Err(Denied::Forbidden(_))));
}

#[test]
fn with_a_token_any_host_name_may_serve_it() {
    let g = gate();
    let h = headers(&[
        (header::HOST, "dray.example.org"),
        (header::AUTHORIZATION, &format!("Bearer {TOKEN}")),
    ]);
    assert_eq!(g.authenticate(&h, at(0)), Ok(Credential::Bearer));
}
