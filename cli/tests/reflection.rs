//! A client written by others drives a real `dray coordinator`: Python `grpcio` with
//! `grpcio-reflection` (cli/tests/python/reflection_client.py), which learns the API only
//! from gRPC server reflection, as grpcurl does. It submits a job given as proto3 JSON,
//! watches it to the end and fetches the PNG, which must be the bytes `dray render` writes
//! with the same settings.
//!
//! The Python interpreter comes from `DRAY_PY` (the venv .ci/run builds from
//! cli/tests/python/requirements.txt). Without it the test says it is skipped and passes,
//! so `cargo test` works on a machine without Python; .ci/run always sets it.

mod common;
mod support;

use std::process::Command;

#[test]
fn python_reflection_client_renders_the_same_png_as_dray_render() {
    let Some(python) = std::env::var_os("DRAY_PY") else {
        common::dependency_missing("DRAY_PY not set (.ci/run sets it to its Python venv)");
        return;
    };
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/python/reflection_client.py"
    );
    let dir = common::tmp("reflection");
    let server = support::coordinator(&dir);

    let (w, h) = (56u32, 40u32);
    // proto3 JSON, as grpcurl takes it: lowerCamelCase names, 64-bit integers as strings,
    // optional fields present.
    let spec = format!(
        r#"{{"scene":"cornell:mirror","width":{w},"height":{h},"spp":3,"integrator":"path","maxDepth":4,"seed":"11","env":{{"r":0.1,"g":0.2,"b":0.3}},"label":"python reflection test"}}"#
    );
    let png = dir.join("python.png");
    let out = Command::new(&python)
        .arg(script)
        .args(["--addr", &server.addr, "--spec", &spec, "--out"])
        .arg(&png)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", python.to_string_lossy()));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "reflection client failed ({}):\nstdout: {stdout}\nstderr: {stderr}",
        out.status
    );
    let summary: serde_json::Value = serde_json::from_str(stdout.trim())
        .unwrap_or_else(|e| panic!("summary is not JSON ({e}): {stdout}"));
    eprintln!("python client summary: {summary}");
    let services = summary["services"].as_array().expect("services");
    assert!(
        services.iter().any(|s| s == "dray.v1.RenderService"),
        "{summary}"
    );
    assert!(
        services.iter().any(|s| s == "grpc.health.v1.Health"),
        "{summary}"
    );
    assert_eq!(
        summary["invalid_spp"]["code"], "INVALID_ARGUMENT",
        "{summary}"
    );
    assert!(
        summary["invalid_spp"]["message"]
            .as_str()
            .is_some_and(|m| m.starts_with("spp")),
        "{summary}"
    );
    assert_eq!(summary["final_state"], "JOB_STATE_SUCCEEDED", "{summary}");
    assert_eq!(summary["tiles_done"], summary["tiles_total"], "{summary}");
    assert!(
        summary["rays_traced"].as_u64().is_some_and(|n| n > 0),
        "{summary}"
    );
    assert_eq!(summary["content_type"], "image/png", "{summary}");
    assert_eq!(
        (summary["width"].as_u64(), summary["height"].as_u64()),
        (Some(w.into()), Some(h.into()))
    );

    let got = std::fs::read(&png).expect("the client's PNG");
    let img = image::load_from_memory(&got).expect("the client's PNG decodes");
    assert_eq!((img.width(), img.height()), (w, h));

    let reference = common::render(
        &dir,
        "reference",
        "cornell:mirror",
        &[
            "--width",
            &w.to_string(),
            "--height",
            &h.to_string(),
            "--spp",
            "3",
            "--integrator",
            "path",
            "--max-depth",
            "4",
            "--seed",
            "11",
            "--env",
            "0.1,0.2,0.3",
        ],
    );
    assert!(reference.ok, "{}", reference.stderr);
    let want = std::fs::read(reference.png.expect("png")).expect("reference png");
    assert!(
        got == want,
        "the PNG fetched by the Python client differs from dray render's"
    );
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}
