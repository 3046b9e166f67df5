//! Which credential each gRPC method needs, checked by a tower layer in front of every
//! service of a server ([`AuthLayer`]).
//!
//! The class comes from the request path (`/package.Service/Method`), so a service
//! cannot be added to a server without being classed: anything not known to be open
//! or public is a cluster service.

use std::sync::Arc;
use std::task::{Context, Poll};

use tonic::Status;
use tower::{Layer, Service};

use crate::credential::Token;

/// The metadata key of a worker's own secret (RegisterWorkerResponse.member_token),
/// sent by the worker with every call that speaks for it and checked by the
/// coordinator: one constant for both sides.
pub const MEMBER_HEADER: &str = "x-dray-member";

/// Who may call a method.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Anyone: health checks (probes) and server reflection (grpcurl's discovery).
    Open,
    /// Holders of the API token: the public API.
    Api,
    /// Holders of the cluster token: the cluster's own members.
    Cluster,
}

/// The access class of a request path.
pub fn access_of(path: &str) -> Access {
    let service = path
        .strip_prefix('/')
        .and_then(|p| p.split('/').next())
        .unwrap_or("");
    match service {
        "grpc.health.v1.Health"
        | "grpc.reflection.v1.ServerReflection"
        | "grpc.reflection.v1alpha.ServerReflection" => Access::Open,
        "dray.v1.RenderService" => Access::Api,
        _ => Access::Cluster,
    }
}

/// The tokens a server accepts. A class without a token is open (a cluster on
/// loopback, a laptop); `dray` says so at start-up.
#[derive(Clone, Debug, Default)]
pub struct AuthPolicy {
    pub api: Option<Token>,
    pub cluster: Option<Token>,
}

/// Why a policy cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error(
        "the API token and the cluster token are the same: API clients would hold the cluster's credential"
    )]
    SameToken,
}

impl AuthPolicy {
    /// Check the policy: the two tokens must differ.
    pub fn checked(self) -> Result<AuthPolicy, PolicyError> {
        if let (Some(a), Some(c)) = (&self.api, &self.cluster)
            && a == c
        {
            return Err(PolicyError::SameToken);
        }
        Ok(self)
    }

    /// Whether a call to `path` with `authorization` header bytes may go on.
    pub fn admit(&self, path: &str, authorization: Option<&[u8]>) -> Result<(), Status> {
        let (token, what) = match access_of(path) {
            Access::Open => return Ok(()),
            Access::Api => (&self.api, "the API token"),
            Access::Cluster => (&self.cluster, "the cluster token"),
        };
        let Some(token) = token else {
            return Ok(());
        };
        let Some(header) = authorization else {
            return Err(Status::unauthenticated(format!(
                "this call needs {what}: send the header \"authorization: Bearer TOKEN\""
            )));
        };
        let presented = header
            .strip_prefix(b"Bearer ")
            .or_else(|| header.strip_prefix(b"bearer "));
        match presented {
            Some(p) if token.matches(p) => Ok(()),
            _ => Err(Status::unauthenticated(format!(
                "this call needs {what}, and the one presented is not it"
            ))),
        }
    }
}

/// The tower layer checking [`AuthPolicy`] before any service sees a request.
#[derive(Clone, Debug)]
pub struct AuthLayer {
    policy: Arc<AuthPolicy>,
}

impl AuthLayer {
    pub fn new(policy: AuthPolicy) -> AuthLayer {
        AuthLayer {
            policy: Arc::new(policy),
        }
    }
}

impl<S> Layer<S> for AuthLayer {
    type Service = Auth<S>;
    fn layer(&self, inner: S) -> Auth<S> {
        Auth {
            inner,
            policy: self.policy.clone(),
        }
    }
}

/// See [`AuthLayer`].
#[derive(Clone, Debug)]
pub struct Auth<S> {
    inner: S,
    policy: Arc<AuthPolicy>,
}

impl<S, B, R> Service<http::Request<B>> for Auth<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    R: Default + Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = std::pin::Pin<
        Box<dyn std::future::Future<Output = Result<http::Response<R>, S::Error>> + Send>,
    >;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        let header = req
            .headers()
            .get(http::header::AUTHORIZATION)
            .map(|v| v.as_bytes());
        match self.policy.admit(req.uri().path(), header) {
            Ok(()) => Box::pin(self.inner.call(req)),
            Err(status) => {
                tracing::warn!(path = %req.uri().path(), "refused: {}", status.message());
                let response = status.into_http::<R>();
                Box::pin(async move { Ok(response) })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tok(s: &str) -> Token {
        Token::parse(s, "test").unwrap()
    }

    #[test]
    fn classes() {
        assert_eq!(access_of("/grpc.health.v1.Health/Check"), Access::Open);
        assert_eq!(
            access_of("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"),
            Access::Open
        );
        assert_eq!(access_of("/dray.v1.RenderService/SubmitJob"), Access::Api);
        assert_eq!(
            access_of("/dray.v1.ClusterService/Register"),
            Access::Cluster
        );
        assert_eq!(
            access_of("/dray.v1.RayExchangeService/RayStream"),
            Access::Cluster
        );
        assert_eq!(access_of("/dray.v1.CacheService/Exchange"), Access::Cluster);
        // Scene package files are the cluster's, never the API clients'.
        assert_eq!(
            access_of("/dray.v1.PackageService/FetchFile"),
            Access::Cluster
        );
        assert_eq!(access_of("/something.Else/X"), Access::Cluster);
        assert_eq!(access_of("garbage"), Access::Cluster);
    }

    #[test]
    fn admits_only_the_right_token_for_the_class() {
        let p = AuthPolicy {
            api: Some(tok("api-token-0123456789")),
            cluster: Some(tok("cluster-token-0123456789")),
        }
        .checked()
        .unwrap();
        let render = "/dray.v1.RenderService/SubmitJob";
        let cluster = "/dray.v1.ClusterService/Heartbeat";
        assert!(
            p.admit(render, Some(b"Bearer api-token-0123456789"))
                .is_ok()
        );
        assert!(p.admit(render, None).is_err());
        assert!(
            p.admit(render, Some(b"Bearer wrong-token-0123456789"))
                .is_err()
        );
        assert!(p.admit(render, Some(b"api-token-0123456789")).is_err());
        // The API token is refused on cluster services, and the other way round.
        assert!(
            p.admit(cluster, Some(b"Bearer api-token-0123456789"))
                .is_err()
        );
        assert!(
            p.admit(render, Some(b"Bearer cluster-token-0123456789"))
                .is_err()
        );
        assert!(
            p.admit(cluster, Some(b"Bearer cluster-token-0123456789"))
                .is_ok()
        );
        assert!(p.admit("/grpc.health.v1.Health/Check", None).is_ok());
        let e = p.admit(render, None).unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated);
        assert!(!e.message().contains("api-token"), "{}", e.message());
        // No tokens: open.
        assert!(AuthPolicy::default().admit(cluster, None).is_ok());
        // Equal tokens are refused.
        let same = AuthPolicy {
            api: Some(tok("same-token-0123456789")),
            cluster: Some(tok("same-token-0123456789")),
        };
        assert!(same.checked().is_err());
    }
}
