//! This worker as a member of the cluster: the id and the member secret the coordinator
//! gave it at registration, and the client that speaks for it.
//!
//! Every call that names the worker carries the secret ([`Member::as_member`]), so that
//! no other process can speak for it; the id and secret change together when the worker
//! registers again (a restarted coordinator, or one that declared it lost). Only this
//! file holds them.

use std::sync::RwLock;

use dray_net::AuthChannel;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::{GetPeerPassRequest, GetRoutingTableRequest, RoutingTable};

use dray_net::auth::MEMBER_HEADER;

/// The worker's membership: who it is at the coordinator, and its client there.
pub(crate) struct Member {
    id: RwLock<String>,
    /// The coordinator's secret for this worker (RegisterWorkerResponse.member_token),
    /// sent with every call that names the worker.
    secret: RwLock<String>,
    client: ClusterServiceClient<AuthChannel>,
}

impl Member {
    /// Not registered yet: no id and no secret.
    pub fn new(channel: AuthChannel) -> Member {
        Member {
            id: RwLock::new(String::new()),
            secret: RwLock::new(String::new()),
            client: ClusterServiceClient::new(channel),
        }
    }

    /// This worker's id at the coordinator (changes when it registers again).
    pub fn id(&self) -> String {
        dray_sync::read(&self.id).clone()
    }

    /// Take the id and secret the coordinator gave at registration.
    pub fn set_member(&self, id: &str, token: &str) {
        *dray_sync::write(&self.id) = id.to_string();
        *dray_sync::write(&self.secret) = token.to_string();
    }

    /// The client to the coordinator (a cheap clone of one channel). Calls that name
    /// the worker wrap their message in [`Member::as_member`].
    pub fn client(&self) -> ClusterServiceClient<AuthChannel> {
        self.client.clone()
    }

    /// `msg` as a request speaking for this worker: with its member secret attached.
    pub fn as_member<T>(&self, msg: T) -> tonic::Request<T> {
        let mut req = tonic::Request::new(msg);
        let token = dray_sync::read(&self.secret).clone();
        if let Ok(v) = tonic::metadata::MetadataValue::try_from(token.as_str())
            && !token.is_empty()
        {
            req.metadata_mut().insert(MEMBER_HEADER, v);
        }
        req
    }

    /// The pass that lets this worker open a ray stream to `peer_id` (the receiver
    /// checks it: only the coordinator can make one; see `dray_net::peer_pass`).
    pub async fn peer_pass(&self, peer_id: &str) -> Result<String, tonic::Status> {
        let r = self
            .client()
            .get_peer_pass(self.as_member(GetPeerPassRequest {
                worker_id: self.id(),
                peer_id: peer_id.to_string(),
            }))
            .await?;
        Ok(r.into_inner().pass)
    }

    /// The whole current routing table of `job_id`, from the coordinator (None when it
    /// has none: the job is not running there).
    pub async fn whole_table(&self, job_id: &str) -> Option<RoutingTable> {
        let r = self
            .client()
            .get_routing_table(self.as_member(GetRoutingTableRequest {
                job_id: job_id.to_string(),
            }))
            .await;
        match r {
            Ok(r) => r.into_inner().routing,
            Err(s) => {
                tracing::warn!(job = %job_id, "could not fetch the whole routing table: {}", s.message());
                None
            }
        }
    }
}
