//! `--emulate-link` (docs/caches.md "Pricing communication: the emulated interconnect"):
//! `dray cluster` hands the spec to every member,
//! each member's servers shape the connections they accept, and a job rendered through
//! the emulated links has the same bits as `dray render`; a bad spec is refused naming
//! what is wrong.

mod common;
mod support;

use std::process::Stdio;

use support::dray;

const SLOT: u16 = 0;

#[test]
fn a_cluster_on_emulated_links_shapes_every_member_and_renders_the_same_bits() {
    let dir = common::tmp("emulated-link");
    let cluster = support::WorkerCluster::start(
        2,
        SLOT,
        &dir,
        &["--emulate-link", "bandwidth=100mbit,latency=2ms"],
    );
    let flags = [
        "--width",
        "32",
        "--height",
        "24",
        "--spp",
        "2",
        "--domains",
        "4",
    ];
    let png = dir.join("emulated.png");
    let out = dray()
        .args(["submit", "--coordinator", &cluster.addr, "cornell", "-q"])
        .args(flags)
        .arg("--output")
        .arg(&png)
        .stdin(Stdio::null())
        .output()
        .expect("run dray submit");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let reference = common::render(&dir, "reference", "cornell", &flags);
    assert!(reference.ok, "{}", reference.stderr);
    assert!(
        std::fs::read(&png).expect("png")
            == std::fs::read(reference.png.expect("png")).expect("png"),
        "the image through emulated links differs from dray render's"
    );
    // Each member's servers said they shape what they accept, with the spec as given:
    // the coordinator's and at least one per worker.
    let log = cluster.log();
    let shaped = log
        .lines()
        .filter(|l| {
            l.contains("every connection this server accepts is shaped")
                && l.contains("link=bandwidth=100mbit,latency=2ms")
        })
        .count();
    assert!(shaped >= 3, "{shaped} shaped servers; log:\n{log}");
    drop(cluster);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_bad_link_spec_is_refused_naming_it() {
    for (command, spec, says) in [
        ("worker", "bandwidth=fast", "bandwidth `fast`: needs a unit"),
        ("coordinator", "latency=1h", "latency `1h`: needs a unit"),
        ("cache", "delay=1ms", "unknown key `delay`"),
        ("cluster", "", "an empty link emulation"),
    ] {
        let out = dray()
            .args([command, "--emulate-link", spec])
            .stdin(Stdio::null())
            .output()
            .expect("run dray");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "dray {command} took {spec:?}");
        assert!(
            err.contains(says),
            "dray {command} --emulate-link {spec:?}: {err}"
        );
    }
}
