//! "Did you mean …?" for a scene spec that names nothing: the closest procedural scene
//! name, or the closest scene file in the folder the spec points into. A typo such as
//! `cornel` or `bunny.pyl` is then one glance from its fix.

use std::path::Path;

/// Procedural specs a user types, as they are typed (`spheres:N` is suggested as
/// `spheres:100`, a spec that runs).
const PROCEDURAL_EXAMPLES: [&str; 8] = [
    "cornell",
    "cornell:mirror",
    "cornell:glass",
    "spheres:100",
    "soup:1000",
    "city:4",
    "iso:gyroid:64",
    "grid:cornell:2x2x2",
];

/// Scene files a suggestion may name.
const SCENE_EXTENSIONS: [&str; 4] = ["gltf", "glb", "ply", "obj"];

/// The suggestion for `spec`, a spec that is neither a file nor a procedural name, or
/// `None` when nothing is close (at most a third of the spec's characters differ, and
/// at most 3).
pub fn suggest(spec: &str) -> Option<String> {
    closest(spec, files_beside(spec))
}

/// The closest procedural spec only: for a coordinator, whose paths are relative to
/// its scene root and whose folders a client may not list.
pub fn suggest_procedural(spec: &str) -> Option<String> {
    closest(spec, Vec::new())
}

fn closest(spec: &str, files: Vec<String>) -> Option<String> {
    let limit = (spec.chars().count() / 3).clamp(1, 3);
    let mut candidates: Vec<String> = PROCEDURAL_EXAMPLES.iter().map(|s| s.to_string()).collect();
    candidates.extend(files);
    candidates
        .into_iter()
        .filter(|c| c != spec)
        .map(|c| (strsim::damerau_levenshtein(spec, &c), c))
        .filter(|(d, _)| *d <= limit)
        .min()
        .map(|(_, c)| c)
}

/// Scene files in the folder `spec` points into, spelled as `spec` spells its folder.
fn files_beside(spec: &str) -> Vec<String> {
    let path = Path::new(spec);
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let Ok(entries) = std::fs::read_dir(folder) else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| SCENE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        })
        .filter_map(|p| {
            let name = p.file_name()?.to_str()?.to_string();
            Some(match path.parent() {
                Some(f) if !f.as_os_str().is_empty() => f.join(name).to_str()?.to_string(),
                _ => name,
            })
        })
        .take(10_000)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_procedural_typo_is_suggested() {
        assert_eq!(suggest("cornel").as_deref(), Some("cornell"));
        assert_eq!(suggest("cornell:miror").as_deref(), Some("cornell:mirror"));
    }

    #[test]
    fn a_file_typo_in_its_folder_is_suggested() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("bunny.ply"), b"").expect("write");
        let spec = dir.path().join("bunny.pyl");
        let want = dir.path().join("bunny.ply");
        assert_eq!(
            suggest(spec.to_str().expect("utf-8")).as_deref(),
            want.to_str()
        );
    }

    #[test]
    fn nothing_close_gives_none() {
        assert_eq!(suggest("/no/such/folder/zzzzzzzzzzzz.glb"), None);
        assert_eq!(suggest("q"), None);
    }
}
