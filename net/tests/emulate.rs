//! The emulated interconnect on a real server: a tonic client calls a dray server
//! (`dray_net::server::serve`) whose accepted connections are shaped, in plaintext and
//! over TLS (the shaping sits beneath TLS), and every call still succeeds, no sooner than
//! its request and its response have each waited out the link's latency.

mod support;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use dray_net::{ClientOptions, LinkEmulation, ServerOptions, TlsFiles};
use dray_proto::v1::GetJobRequest;
use dray_proto::v1::render_service_client::RenderServiceClient;
use support::start;

const LATENCY: Duration = Duration::from_millis(25);

fn shaped(tls: &TlsFiles) -> ServerOptions {
    let mut o = ServerOptions::new(None, None, tls).expect("server options");
    o.emulate = Some(LinkEmulation {
        bandwidth_bits_per_s: Some(1_000_000_000),
        latency: LATENCY,
    });
    o
}

/// Three GetJob calls on one connection (after one that opens it): each succeeds and
/// takes at least twice the latency (the request in, the response out).
async fn round_trips_wait_out_the_link(server_tls: &TlsFiles, client_tls: &TlsFiles) {
    let server = start(shaped(server_tls)).await;
    let client = ClientOptions::new(None, client_tls).expect("client options");
    let channel = client
        .endpoint(&server.addr.to_string())
        .expect("endpoint")
        .connect()
        .await
        .expect("connect through the shaped link");
    let mut api = RenderServiceClient::new(channel);
    api.get_job(GetJobRequest::default())
        .await
        .expect("the first call");
    for i in 0..3 {
        let t0 = Instant::now();
        api.get_job(GetJobRequest::default())
            .await
            .expect("a call through the shaped link");
        let took = t0.elapsed();
        assert!(
            took >= 2 * LATENCY,
            "call {i} took {took:?}, less than a round trip of {:?}",
            2 * LATENCY
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unary_call_pays_a_round_trip_in_plaintext() {
    round_trips_wait_out_the_link(&TlsFiles::default(), &TlsFiles::default()).await;
}

/// A temporary directory, removed when dropped.
struct Dir(PathBuf);
impl Drop for Dir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unary_call_pays_a_round_trip_over_tls() {
    let d = Dir(std::env::temp_dir().join(format!("dray-emulate-tls-{}", std::process::id())));
    let _ = std::fs::remove_dir_all(&d.0);
    std::fs::create_dir(&d.0).expect("a temporary directory");
    let key = rcgen::KeyPair::generate().expect("a key");
    let cert = rcgen::CertificateParams::new(vec!["127.0.0.1".into()])
        .expect("certificate parameters")
        .self_signed(&key)
        .expect("a certificate");
    let (cert_file, key_file) = (d.0.join("cert.pem"), d.0.join("key.pem"));
    std::fs::write(&cert_file, cert.pem()).expect("write the certificate");
    std::fs::write(&key_file, key.serialize_pem()).expect("write the key");
    let server = TlsFiles {
        cert: Some(cert_file.clone()),
        key: Some(key_file),
        ca: None,
    };
    let client = TlsFiles {
        cert: None,
        key: None,
        ca: Some(cert_file),
    };
    round_trips_wait_out_the_link(&server, &client).await;
}
