//! Scene packages held in memory, for a coordinator and workers in one process.
//!
//! `dray render` runs the coordinator and its workers in one process (the embedded mode,
//! so it shares one code path with a cluster). Writing a package to disk there only for
//! the same process to read it back cost more than the render on large scenes: 1.4 s to
//! write 1.7M triangles, plus the read. A [`MemoryPackages`] store replaces the directory:
//! the coordinator partitions the scene into it once, the `JobSetup` names the package
//! `memory:N` instead of a path, and each worker in the process assembles its resident
//! scene from the stored domains, with the very bits a package round trip gives (the
//! domains come from [`partition_in_memory`], which the package tests hold to the disk
//! format).
//!
//! A worker in another process cannot see the store; it gets a clear error naming the
//! package, never another scene.
//!
//! **Kept between jobs.** A store made with [`MemoryPackages::keeping_last`] (`dray
//! sweep`, which renders setting after setting in one process) keeps the last package
//! cut and the scene it was cut from: a job whose scene and layout are equal to those
//! gets the same package name, so the workers, which key resident domains by package,
//! find its domains and BVHs already built instead of loading them again. Equality is of
//! the whole scene (every vertex, material, light and camera), never of its name.
//!
//! **Frames.** A scene that is not equal to the kept one, but has its bounds (the next
//! frame of an animation whose moving meshes stay inside the still ones), is cut with
//! the kept package's layout instead of a new one ([`MemoryPackages::cut`]), and each
//! domain whose triangles are those of the kept package's same domain (with equal
//! tables and emitters) keeps its [content id](MemoryPackage::domain_contents): workers
//! find it resident and only the domains a moving mesh touches are built again. The
//! image does not change: domains never change it, and the bounds, which the light
//! powers read, are the frame's own.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use dray_core::env_map::EnvMap;
use dray_core::scene::{Mesh, Scene};
use dray_sync::lock;

use super::manifest::EMITTERS_DOMAIN;
use super::resident::{ResidentScene, assemble};
use super::{DomainBuilder, DomainLayout, DomainMesh, LayoutSpec, TriangleSource};
use crate::error::Result;

/// The prefix of an in-memory package's name, where a package path would be.
pub const MEMORY_PREFIX: &str = "memory:";

/// Whether `path` names an in-memory package rather than a directory.
pub fn is_memory_package(path: &str) -> bool {
    path.starts_with(MEMORY_PREFIX)
}

/// A partitioned scene in memory: what a package directory holds, as values.
pub struct MemoryPackage {
    /// The scene's tables (materials, textures, lights, cameras, environment); no mesh.
    tables: Scene,
    /// The layout the scene was cut with.
    layout: DomainLayout,
    /// Each domain's triangles, by domain index (empty domains have no triangles).
    domains: Vec<DomainMesh>,
    /// Every emissive triangle, for next-event estimation on any worker.
    emitters: DomainMesh,
    /// What each domain is, by domain index: unique in the process, or the id of an
    /// equal domain of the package this one was cut after ([`MemoryPackages::cut`]).
    contents: Vec<u64>,
}

/// The next domain content id of this process.
static NEXT_CONTENT: AtomicU64 = AtomicU64::new(1);

impl MemoryPackage {
    /// Cut `scene` by `spec`. The scene is consumed: one domain takes its mesh as it is,
    /// several get copies of their triangles.
    pub fn new(scene: Scene, spec: &LayoutSpec) -> Result<MemoryPackage> {
        let layout = DomainLayout::for_source(&scene, spec)?;
        MemoryPackage::with_layout(scene, layout)
    }

    /// Cut `scene` by an existing `layout`.
    pub fn with_layout(mut scene: Scene, layout: DomainLayout) -> Result<MemoryPackage> {
        let b = layout.scene_bounds();
        let mut emitters = DomainBuilder::new();
        let mut domains: Vec<DomainMesh> = (0..layout.domain_count())
            .map(|d| DomainMesh {
                domain: d,
                bounds: layout.bounds(d),
                mesh: Mesh::default(),
                global_ids: Vec::new(),
            })
            .collect();
        if let [only] = domains.as_mut_slice() {
            // One domain holds every triangle, as the scene has them: no assignment to do.
            only.global_ids = (0..scene.mesh.triangle_count() as u32).collect();
            only.mesh = std::mem::take(&mut scene.mesh);
            emitters_of(&only.mesh, &scene, &mut emitters)?;
        } else {
            for part in super::partition_in_memory(&scene, &layout)? {
                if let Some(slot) = domains.get_mut(part.domain as usize) {
                    *slot = part;
                }
            }
            emitters_of(&scene.mesh, &scene, &mut emitters)?;
        }
        scene.mesh = Mesh::default();
        let tables = scene;
        let contents = (0..domains.len())
            .map(|_| NEXT_CONTENT.fetch_add(1, Ordering::Relaxed))
            .collect();
        Ok(MemoryPackage {
            tables,
            layout,
            domains,
            emitters: emitters.finish(EMITTERS_DOMAIN, b),
            contents,
        })
    }

    /// What each domain is, by domain index: equal ids are equal domains (box,
    /// triangles, tables, emitters, bounds), so a worker may use one loaded for
    /// another package.
    pub fn domain_contents(&self) -> &[u64] {
        &self.contents
    }

    /// Give each domain equal to `old`'s domain of the same index, in a package of
    /// the same layout, tables and emitters, `old`'s content id. Returns how many.
    fn inherit(&mut self, old: &MemoryPackage) -> usize {
        if self.layout != old.layout || self.emitters != old.emitters || self.tables != old.tables {
            return 0;
        }
        let mut same = 0;
        for ((mine, id), (theirs, old_id)) in self
            .domains
            .iter()
            .zip(self.contents.iter_mut())
            .zip(old.domains.iter().zip(&old.contents))
        {
            if mine == theirs {
                *id = *old_id;
                same += 1;
            }
        }
        same
    }

    /// The layout every worker walks rays with.
    pub fn layout(&self) -> &DomainLayout {
        &self.layout
    }

    /// The number of domains.
    pub fn domain_count(&self) -> u32 {
        self.layout.domain_count()
    }

    /// Domain `d`'s triangles, if the layout has it.
    pub fn domain_mesh(&self, d: u32) -> Option<&DomainMesh> {
        self.domains.get(d as usize)
    }

    /// Every emissive triangle, in scene order.
    pub fn emitters(&self) -> &DomainMesh {
        &self.emitters
    }

    /// The scene's tables (cameras, materials, ...), with no triangles.
    pub fn tables(&self) -> &Scene {
        &self.tables
    }

    /// Triangles per domain, by domain index.
    pub fn triangle_counts(&self) -> Vec<u64> {
        self.domains
            .iter()
            .map(|d| d.triangle_count() as u64)
            .collect()
    }

    /// What a worker owning `owned` holds: the same resident scene
    /// [`super::load_resident`] assembles from a package of this scene and layout.
    /// Domains not in the layout are an error.
    pub fn resident(&self, owned: &[u32]) -> Result<ResidentScene> {
        let parts = owned
            .iter()
            .map(|&d| {
                self.domains.get(d as usize).cloned().ok_or_else(|| {
                    super::layout::layout_error(format!(
                        "domain {d} is not in the package ({} domains)",
                        self.domains.len()
                    ))
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let b = self.layout.scene_bounds();
        Ok(assemble(
            self.tables.clone(),
            (b.min, b.max),
            parts,
            self.emitters.clone(),
        ))
    }
}

/// Push every emissive triangle of `mesh` (whose materials are `scene`'s) to `out`.
fn emitters_of(mesh: &Mesh, scene: &Scene, out: &mut DomainBuilder) -> Result<()> {
    // A scene with no emissive material (most: sun, sky, point lights) has none: no need
    // to visit its triangles.
    if !scene.materials.iter().any(|m| m.has_emission()) {
        return Ok(());
    }
    mesh.for_each_triangle(&mut |t| {
        if scene
            .materials
            .get(t.material as usize)
            .is_some_and(|m| m.has_emission())
        {
            out.push(t);
        }
        Ok(())
    })
}

/// The in-memory packages of one process, by name, and the decoded environment maps of
/// their jobs (`--env-map`: workers in the process take the coordinator's map instead
/// of reading and decoding the file again).
#[derive(Default)]
pub struct MemoryPackages {
    packages: Mutex<HashMap<String, Arc<MemoryPackage>>>,
    env_maps: Mutex<HashMap<String, Arc<EnvMap>>>,
    next: AtomicU64,
    /// Whether the last package cut is kept for later jobs ([`MemoryPackages::keeping_last`]).
    keeping: bool,
    kept: Mutex<Option<Kept>>,
}

/// The package kept between jobs and what it was cut from.
struct Kept {
    scene: Scene,
    layout: LayoutSpec,
    name: String,
}

impl std::fmt::Debug for MemoryPackages {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MemoryPackages")
            .field("packages", &self.lock().len())
            .finish()
    }
}

impl MemoryPackages {
    /// A store that keeps the last package cut, and the scene it was cut from (a copy:
    /// the cut consumes the job's), for the next job of an equal scene and layout
    /// ([`MemoryPackages::kept`]). For one process rendering one job after another.
    pub fn keeping_last() -> MemoryPackages {
        MemoryPackages {
            keeping: true,
            ..MemoryPackages::default()
        }
    }

    /// Whether this store keeps the last package ([`MemoryPackages::keeping_last`]).
    pub fn keeps(&self) -> bool {
        self.keeping
    }

    /// The name of the kept package, if it was cut from a scene equal to `scene` with
    /// `layout`.
    pub fn kept(&self, scene: &Scene, layout: &LayoutSpec) -> Option<String> {
        let kept = lock(&self.kept);
        kept.as_ref()
            .filter(|k| k.layout == *layout && k.scene == *scene)
            .map(|k| k.name.clone())
    }

    /// Keep the package `name`, cut from `scene` with `layout`, for later jobs (a store
    /// that does not keep packages ignores it). The package kept before is forgotten
    /// (workers still using it hold their own handle).
    pub fn keep(&self, name: &str, scene: Scene, layout: LayoutSpec) {
        if !self.keeping {
            return;
        }
        let old = lock(&self.kept).replace(Kept {
            scene,
            layout,
            name: name.to_string(),
        });
        if let Some(old) = old
            && old.name != name
        {
            self.remove(&old.name);
        }
    }

    /// Cut `scene` by `spec` (see "Frames" above): with the kept package's layout when
    /// this store keeps one of the same spec and `scene` has its bounds, each domain
    /// equal to the kept one's keeping its content id; else as [`MemoryPackage::new`].
    pub fn cut(&self, scene: Scene, spec: &LayoutSpec) -> Result<MemoryPackage> {
        let kept = lock(&self.kept)
            .as_ref()
            .filter(|k| k.layout == *spec)
            .and_then(|k| self.get(&k.name));
        let Some(old) = kept else {
            return MemoryPackage::new(scene, spec);
        };
        if super::survey(&scene.mesh, 0)?.bounds != old.layout.scene_bounds() {
            return MemoryPackage::new(scene, spec);
        }
        let mut pkg = MemoryPackage::with_layout(scene, old.layout.clone())?;
        let same = pkg.inherit(&old);
        tracing::info!(
            domains = pkg.domain_count(),
            same,
            "cut with the kept package's layout; domains equal to its own kept"
        );
        Ok(pkg)
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<String, Arc<MemoryPackage>>> {
        lock(&self.packages)
    }

    /// A fresh name, `memory:N`.
    fn fresh_name(&self) -> String {
        format!(
            "{MEMORY_PREFIX}{}",
            self.next.fetch_add(1, Ordering::Relaxed) + 1
        )
    }

    /// Keep `package` under a fresh name (`memory:N`) and return the name.
    pub fn insert(&self, package: MemoryPackage) -> String {
        let name = self.fresh_name();
        self.lock().insert(name.clone(), Arc::new(package));
        name
    }

    /// Keep a job's decoded environment map under a fresh name (`memory:N`), which
    /// [`MemoryPackages::remove`] forgets, and return the name.
    pub fn insert_env_map(&self, map: Arc<EnvMap>) -> String {
        let name = self.fresh_name();
        lock(&self.env_maps).insert(name.clone(), map);
        name
    }

    /// The environment map called `name`, if this process holds it.
    pub fn env_map(&self, name: &str) -> Option<Arc<EnvMap>> {
        lock(&self.env_maps).get(name).cloned()
    }

    /// The package called `name`, if this process holds it.
    pub fn get(&self, name: &str) -> Option<Arc<MemoryPackage>> {
        self.lock().get(name).cloned()
    }

    /// Forget `name` (its memory goes when the last worker drops its handle).
    pub fn remove(&self, name: &str) {
        self.lock().remove(name);
        lock(&self.env_maps).remove(name);
    }

    /// Packages held.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// Whether no package is held.
    pub fn is_empty(&self) -> bool {
        self.lock().is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(name: &str, x: f32) -> Scene {
        let mut s = Scene {
            name: name.into(),
            ..Scene::default()
        };
        s.mesh.positions.push(glam::Vec3::new(x, 0.0, 0.0));
        s
    }

    #[test]
    fn a_keeping_store_finds_the_last_package_by_scene_and_layout() {
        let store = MemoryPackages::keeping_last();
        assert!(store.keeps());
        let kd = LayoutSpec::Kd(4);
        assert_eq!(store.kept(&scene("a", 1.0), &kd), None);
        store.keep("memory:1", scene("a", 1.0), kd);
        assert_eq!(
            store.kept(&scene("a", 1.0), &kd).as_deref(),
            Some("memory:1")
        );
        // Another vertex, another layout: not the same package.
        assert_eq!(store.kept(&scene("a", 1.5), &kd), None);
        assert_eq!(store.kept(&scene("a", 1.0), &LayoutSpec::Kd(8)), None);
        // A new package replaces the kept one, which the store forgets.
        let map = EnvMap::new(1, 1, vec![glam::Vec3::ONE], 0.0, 1.0).unwrap();
        lock(&store.env_maps).insert("memory:1".into(), Arc::new(map));
        store.keep("memory:2", scene("b", 2.0), kd);
        assert_eq!(store.kept(&scene("a", 1.0), &kd), None);
        assert_eq!(
            store.kept(&scene("b", 2.0), &kd).as_deref(),
            Some("memory:2")
        );
        assert!(
            store.env_map("memory:1").is_none(),
            "the replaced package is forgotten"
        );
    }

    /// A ground quad split across a 2x1x1 grid and a small triangle in the +x half:
    /// moving the triangle keeps the -x domain's content, the +x domain's changes.
    #[test]
    fn a_moved_mesh_changes_only_the_domains_it_touches() {
        let frame = |x: f32| {
            let mut s = Scene::default();
            let p = |x, y, z| glam::Vec3::new(x, y, z);
            s.mesh.positions = vec![
                p(-2.0, 0.0, -2.0),
                p(2.0, 0.0, -2.0),
                p(2.0, 0.0, 2.0),
                p(-2.0, 0.0, 2.0),
                p(x - 0.1, 0.0, 0.0),
                p(x + 0.1, 0.0, 0.0),
                p(x, 1.0, 0.0),
            ];
            s.mesh.indices = vec![[0, 2, 1], [0, 3, 2], [4, 5, 6]];
            s.mesh.material = vec![0; 3];
            s
        };
        let grid = LayoutSpec::Grid([2, 1, 1]);
        let store = MemoryPackages::keeping_last();
        let first = store.cut(frame(1.2), &grid).unwrap();
        let ids0 = first.domain_contents().to_vec();
        let name = store.insert(first);
        store.keep(&name, frame(1.2), grid);
        let second = store.cut(frame(1.5), &grid).unwrap();
        let ids1 = second.domain_contents();
        assert_eq!(ids1[0], ids0[0], "the -x half did not change");
        assert_ne!(ids1[1], ids0[1], "the triangle moved in the +x half");
        // Bounds that differ: a layout of its own, no domain shared.
        let far = store.cut(frame(3.0), &grid).unwrap();
        assert!(far.domain_contents().iter().all(|c| !ids0.contains(c)));
        // A store that keeps nothing shares nothing.
        let plain = MemoryPackages::default();
        let a = plain.cut(frame(1.2), &grid).unwrap();
        let b = plain.cut(frame(1.2), &grid).unwrap();
        assert_ne!(a.domain_contents(), b.domain_contents());
    }

    #[test]
    fn a_plain_store_keeps_nothing() {
        let store = MemoryPackages::default();
        assert!(!store.keeps());
        store.keep("memory:1", scene("a", 1.0), LayoutSpec::Kd(4));
        assert_eq!(store.kept(&scene("a", 1.0), &LayoutSpec::Kd(4)), None);
    }
}
