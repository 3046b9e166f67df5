//! TLS end to end, with certificates made inside the test (rcgen): a certificate
//! authority, one certificate for the cluster's members (valid for 127.0.0.1) and one for
//! a client. `dray cluster --tls-cert --tls-key --tls-ca` serves every member over TLS
//! and, because the CA is given, requires client certificates it signed (mutual TLS):
//!
//! - `dray submit` with the CA and its client certificate renders the image of
//!   `dray render`, bit for bit (the members' own calls went over TLS too: the job ran);
//! - in plaintext, or over TLS without a client certificate, it is refused, in one line.

mod common;
mod support;

use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};

use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair};
use support::{Proc, dray};

/// Slot of this binary's one cluster (see support::cluster_base_port).
const SLOT: u16 = 0;
/// A limit that only catches hangs.
const HANG_SECS: f64 = 120.0;

/// The PEM files of a CA and two certificates it signed.
struct Pki {
    ca: PathBuf,
    server_cert: PathBuf,
    server_key: PathBuf,
    client_cert: PathBuf,
    client_key: PathBuf,
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write pem");
    p
}

fn make_pki(dir: &Path) -> Pki {
    let ca_key = KeyPair::generate().expect("ca key");
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).expect("ca params");
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca_cert = ca_params.self_signed(&ca_key).expect("ca cert");
    let issuer = Issuer::new(ca_params, ca_key);
    let leaf = |names: Vec<String>| {
        let key = KeyPair::generate().expect("key");
        let cert = CertificateParams::new(names)
            .expect("params")
            .signed_by(&key, &issuer)
            .expect("sign");
        (cert.pem(), key.serialize_pem())
    };
    let (server_cert, server_key) = leaf(vec!["127.0.0.1".into(), "localhost".into()]);
    let (client_cert, client_key) = leaf(vec!["dray-test-client".into()]);
    Pki {
        ca: write(dir, "ca.pem", &ca_cert.pem()),
        server_cert: write(dir, "server.pem", &server_cert),
        server_key: write(dir, "server.key", &server_key),
        client_cert: write(dir, "client.pem", &client_cert),
        client_key: write(dir, "client.key", &client_key),
    }
}

fn job_flags() -> Vec<&'static str> {
    vec![
        "cornell:mirror",
        "--width",
        "32",
        "--height",
        "24",
        "--spp",
        "2",
        "--seed",
        "9",
        "--integrator",
        "path",
        "--max-depth",
        "4",
    ]
}

fn submit(addr: &str, png: &Path, tls: &[&Path]) -> Output {
    let mut cmd = dray();
    cmd.args(["submit", "--coordinator", addr])
        .args(job_flags())
        .arg("--output")
        .arg(png);
    for (flag, path) in ["--tls-ca", "--tls-cert", "--tls-key"].iter().zip(tls) {
        cmd.arg(flag).arg(path);
    }
    for v in ["DRAY_TLS_CA", "DRAY_TLS_CERT", "DRAY_TLS_KEY"] {
        cmd.env_remove(v);
    }
    cmd.stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let mut p = Proc::spawn(cmd);
    let status = p
        .wait_timeout(HANG_SECS)
        .unwrap_or_else(|| panic!("HANG: dray submit did not finish in {HANG_SECS} s"));
    let mut stderr = Vec::new();
    if let Some(mut e) = p.child.stderr.take() {
        let _ = std::io::Read::read_to_end(&mut e, &mut stderr);
    }
    Output {
        status,
        stdout: Vec::new(),
        stderr,
    }
}

#[test]
fn a_cluster_over_mutual_tls_renders_the_same_bits_and_refuses_plaintext() {
    let dir = common::tmp("tls");
    let pki = make_pki(&dir);
    let flags: Vec<String> = [
        ("--tls-cert", &pki.server_cert),
        ("--tls-key", &pki.server_key),
        ("--tls-ca", &pki.ca),
    ]
    .iter()
    .flat_map(|(f, p)| [f.to_string(), p.display().to_string()])
    .collect();
    let flag_refs: Vec<&str> = flags.iter().map(String::as_str).collect();
    let cluster = support::WorkerCluster::start(2, SLOT, &dir, &flag_refs);

    let want = common::render(&dir, "want", "cornell:mirror", &job_flags()[1..]);
    assert!(want.ok, "{}", want.stderr);
    let want = std::fs::read(want.png.expect("png")).expect("read png");

    let png = dir.join("tls.png");
    let out = submit(
        &cluster.addr,
        &png,
        &[&pki.ca, &pki.client_cert, &pki.client_key],
    );
    assert!(
        out.status.success(),
        "over TLS: {}\ncluster log:\n{}",
        String::from_utf8_lossy(&out.stderr),
        cluster.log()
    );
    let got = std::fs::read(&png).expect("submit png");
    assert!(got == want, "the image over TLS differs from dray render's");

    for (what, tls) in [
        ("plaintext", vec![]),
        ("TLS without a client certificate", vec![pki.ca.as_path()]),
    ] {
        let png = dir.join("refused.png");
        let out = submit(&cluster.addr, &png, &tls);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{what}: it succeeded");
        assert_eq!(err.trim_end().lines().count(), 1, "{what}: {err:?}");
        assert!(err.starts_with("dray: error: "), "{what}: {err}");
        assert!(!png.exists(), "{what}: an image was written");
    }
    assert!(cluster.all_alive(), "{}", cluster.log());
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Run `dray args...` to its end (it must end: each case fails before serving).
fn run_to_end(args: &[&str]) -> (std::process::ExitStatus, String, String) {
    let mut cmd = dray();
    cmd.args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    for v in ["DRAY_TLS_CA", "DRAY_TLS_CERT", "DRAY_TLS_KEY"] {
        cmd.env_remove(v);
    }
    let mut p = Proc::spawn(cmd);
    let (mut out, mut err) = (Vec::new(), Vec::new());
    // Read both pipes to their end (the process closes them when it exits).
    let mut stdout = p.child.stdout.take().expect("stdout");
    let reader = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = std::io::Read::read_to_end(&mut stdout, &mut v);
        v
    });
    if let Some(mut e) = p.child.stderr.take() {
        let _ = std::io::Read::read_to_end(&mut e, &mut err);
    }
    let status = p
        .wait_timeout(HANG_SECS)
        .unwrap_or_else(|| panic!("HANG: dray {args:?} still runs after {HANG_SECS} s"));
    out.extend(reader.join().expect("stdout reader"));
    (
        status,
        String::from_utf8_lossy(&out).into_owned(),
        String::from_utf8_lossy(&err).into_owned(),
    )
}

/// docs/security.md "Hardening, second round", item 13: a bad certificate, key or
/// mismatched pair used to print
/// "listening ... TLS" and then fail every handshake with a transport error naming no
/// file; a worker with a mismatched key said "invalid coordinator address". Every
/// server and client now checks its files before it listens or dials.
#[test]
fn bad_tls_files_are_refused_before_listening_naming_the_file() {
    let dir = common::tmp("tls-bad");
    let pki = make_pki(&dir);
    let garbage = write(&dir, "garbage.pem", "this is not PEM\n");
    let s = |p: &PathBuf| p.display().to_string();
    // (what, certificate, key, file the error must name)
    let cases = [
        (
            "a key of another certificate",
            &pki.server_cert,
            &pki.client_key,
            "client.key",
        ),
        (
            "a certificate that is not PEM",
            &garbage,
            &pki.server_key,
            "garbage.pem",
        ),
        (
            "a key that is not PEM",
            &pki.server_cert,
            &garbage,
            "garbage.pem",
        ),
    ];
    for (what, cert, key, named) in cases {
        let (cert, key, ca) = (s(cert), s(key), s(&pki.ca));
        let tls = ["--tls-cert", &cert, "--tls-key", &key, "--tls-ca", &ca];
        let coordinator: Vec<&str> = ["coordinator", "--listen", "127.0.0.1:0"]
            .into_iter()
            .chain(tls)
            .collect();
        let worker: Vec<&str> = [
            "worker",
            "--listen",
            "127.0.0.1:0",
            "--coordinator",
            "127.0.0.1:9",
        ]
        .into_iter()
        .chain(tls)
        .collect();
        for args in [coordinator, worker] {
            let (status, out, err) = run_to_end(&args);
            assert!(!status.success(), "{what}, {}: it started", args[0]);
            assert!(!out.contains("listening"), "{what}, {}: {out}", args[0]);
            assert!(
                err.starts_with("dray: error: "),
                "{what}, {}: {err}",
                args[0]
            );
            assert!(err.contains(named), "{what}, {}: {err}", args[0]);
            assert!(!err.contains("panicked"), "{what}, {}: {err}", args[0]);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
