//! The scene package reader (`dray_scene::partition`): `manifest.json` (envelope, body
//! checksum, body, layout, consistency checks) and the binary files it lists (domain
//! files, `emitters.bin`, `textures.bin`), as a worker opens and loads them.
//!
//! The input is a list of files in the framing of `dray_fuzz::Sections`; section ids:
//! - 0: `manifest.json`, written as is (the decoder's own checks, checksums included);
//! - 1: a manifest *body* (JSON): parsed as a `Manifest`, then every file checksum it
//!   lists is set to that of the file given here (and, when the first byte of the
//!   input is odd, every size too), and the manifest is written with `manifest::encode`.
//!   This takes the fuzzer past the checksums to the decoding and index checks behind
//!   them, which it could never reach by guessing a 64-bit hash;
//! - 2: `textures.bin`; 3: `emitters.bin`; 4 + d: `domain-<d>.bin`.
//!
//! The first byte of the input is a flags byte, the sections follow it. Everything
//! is written to a per-process scratch directory, then `open_package`, `verify`,
//! `tables` and `load_resident` of every domain (merging, BVH builds) run, and the
//! resident scene is checked with `dray_fuzz::check_scene_with` (positions finite too,
//! since the fix of finding P1 in docs/fuzzing.md; `DRAY_FUZZ_PACKAGE_FINITE=0` turns
//! that check off to look past it on an old build); the layout answers point and box
//! queries.

#![no_main]

use dray_fuzz::{Scratch, Sections, check_scene_with};
use dray_scene::partition::checksum::{checksum, to_hex};
use dray_scene::partition::manifest::{
    self, EMITTERS_FILE, MANIFEST_FILE, Manifest, TEXTURES_FILE, domain_file_name,
};
use dray_scene::partition::{load_resident, open_package};
use glam::Vec3;
use libfuzzer_sys::fuzz_target;

fn finite_check() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("DRAY_FUZZ_PACKAGE_FINITE").is_none_or(|v| v != "0"))
}

/// Domain files beyond this many are ignored (inputs are small anyway).
const MAX_DOMAIN_FILES: u32 = 64;

fuzz_target!(init: dray_fuzz::init("scene_package"), |data: &[u8]| {
    let Some((&flags, rest)) = data.split_first() else {
        return;
    };
    let scratch = Scratch::fresh();
    let mut raw_manifest: Option<&[u8]> = None;
    let mut body: Option<&[u8]> = None;
    let mut textures: Option<&[u8]> = None;
    let mut emitters: Option<&[u8]> = None;
    let mut domains: Vec<(u32, &[u8])> = Vec::new();
    for (id, bytes) in Sections::new(rest) {
        match id {
            0 => raw_manifest = Some(bytes),
            1 => body = Some(bytes),
            2 => textures = Some(bytes),
            3 => emitters = Some(bytes),
            _ => {
                let d = u32::from(id - 4);
                if d < MAX_DOMAIN_FILES && !domains.iter().any(|(e, _)| *e == d) {
                    domains.push((d, bytes));
                }
            }
        }
    }
    for &(d, bytes) in &domains {
        scratch.write(&domain_file_name(d), bytes);
    }
    if let Some(b) = textures {
        scratch.write(TEXTURES_FILE, b);
    }
    if let Some(b) = emitters {
        scratch.write(EMITTERS_FILE, b);
    }
    let text: Vec<u8> = match (raw_manifest, body) {
        (Some(m), _) => m.to_vec(),
        (None, Some(b)) => {
            let Ok(mut m) = serde_json::from_slice::<Manifest>(b) else {
                return;
            };
            let sizes = flags & 1 != 0;
            let fix = |bytes: &[u8], size: &mut u64, xxh3: &mut String| {
                *xxh3 = to_hex(checksum(bytes));
                if sizes {
                    *size = bytes.len() as u64;
                }
            };
            for &(d, bytes) in &domains {
                if let Some(e) = m.domains.get_mut(d as usize) {
                    fix(bytes, &mut e.bytes, &mut e.xxh3);
                }
            }
            if let (Some(bytes), Some(e)) = (emitters, m.emitters.as_mut()) {
                fix(bytes, &mut e.bytes, &mut e.xxh3);
            }
            if let (Some(bytes), Some(e)) = (textures, m.textures_file.as_mut()) {
                fix(bytes, &mut e.bytes, &mut e.xxh3);
            }
            let Ok(text) = manifest::encode(&m) else {
                return;
            };
            text.into_bytes()
        }
        (None, None) => return,
    };
    scratch.write(MANIFEST_FILE, &text);

    let Ok(package) = open_package(scratch.dir()) else {
        return;
    };
    let layout = package.layout();
    let n = package.domain_count();
    assert_eq!(package.manifest().domains.len(), n as usize);
    // Layout queries a worker makes while routing rays.
    let _tree = layout.to_domain_tree();
    let sb = layout.scene_bounds();
    let mut hits = Vec::new();
    for d in 0..n {
        let b = layout.bounds(d);
        for p in [b.min, b.max, (b.min + b.max) * 0.5] {
            if let Some(found) = layout.locate(p) {
                assert!(found < n, "locate gave domain {found} of {n}");
            }
        }
        hits.clear();
        layout.overlapping(&b, &mut hits);
        assert!(hits.iter().all(|&h| h < n));
    }
    hits.clear();
    layout.assign(&[sb.min, sb.max, Vec3::ZERO], &mut hits);
    assert!(hits.iter().all(|&h| h < n));

    let _ = package.tables();
    let verified = package.verify().is_ok();
    let all: Vec<u32> = (0..n).collect();
    let resident = load_resident(&package, &all);
    if verified {
        // verify() checked every file load_resident reads.
        let r = resident.expect("a verified package loads resident");
        // Finding P1 (docs/fuzzing.md, fixed): the reader refuses domain files with
        // non-finite positions, so a verified package has none.
        check_scene_with(&r.scene, finite_check());
        assert_eq!(r.global_ids.len(), r.scene.mesh.indices.len());
        assert!(r.global_ids.windows(2).all(|w| w[0] < w[1]), "global ids ascending");
        assert!(
            r.global_ids
                .iter()
                .all(|&g| u64::from(g) < package.manifest().source_triangles)
        );
    }
});
