//! What one process keeps between renders (`dray sweep` in this process): the loaded
//! scene, and the in-process coordinator and workers with the package they cut and the
//! domains (BVHs) they built.
//!
//! Without it every setting of a sweep loaded the scene again, cut a new package and
//! had every worker load and build every domain again, which a warm cluster does not
//! (its workers keep the last package's domains between jobs): Table 5.1's ray caches
//! then gained less in one process than in a cluster, since each render paid the same
//! fixed cost (docs/benchmarks.md). A render asks [`WarmProcess::scene`] and
//! [`WarmProcess::actors`] instead of loading and starting its own; the image is the
//! same bits, since the scene, package and domains are equal to what a fresh start
//! would make (the coordinator reuses a package only for an equal scene and layout,
//! `MemoryPackages::keeping_last`). The domain loads in each render's statistics
//! (`domain_loads`, `domains_warm`) show the reuse.

use anyhow::Result;
use dray_core::scene::Scene;

use crate::embedded::{Actors, ActorsShape};
use crate::render_cmd::RenderArgs;

/// The flags that decide which scene a render loads: equal keys load equal scenes.
#[derive(Clone, Debug, PartialEq)]
struct SceneKey {
    scene: String,
    time: Option<f64>,
    animation: Option<String>,
    translate: Option<String>,
}

impl SceneKey {
    fn of(a: &RenderArgs) -> SceneKey {
        SceneKey {
            scene: a.job.scene.clone(),
            time: a.job.anim.time,
            animation: a.job.anim.animation.clone(),
            translate: a.job.translate.clone(),
        }
    }
}

/// The scene and actors kept between the renders of one process.
pub struct WarmProcess {
    /// Start every set of actors with a cache host beside each worker, so that a sweep
    /// whose settings differ only in ray caches or hit maps keeps one set.
    cache_hosts: bool,
    scene: Option<(SceneKey, Scene)>,
    actors: Option<Actors>,
}

impl WarmProcess {
    /// Nothing kept yet; `cache_hosts`: start actors with cache hosts (when any render
    /// to come has ray caches or hit maps).
    pub fn new(cache_hosts: bool) -> WarmProcess {
        WarmProcess {
            cache_hosts,
            scene: None,
            actors: None,
        }
    }

    /// The scene `a` names: a copy of the kept one when the last render's flags named
    /// the same (file, time, animation, translation), else `load()`'s, which is kept.
    pub fn scene(&mut self, a: &RenderArgs, load: impl FnOnce() -> Result<Scene>) -> Result<Scene> {
        let key = SceneKey::of(a);
        if let Some((k, scene)) = &self.scene
            && *k == key
        {
            tracing::debug!(scene = %key.scene, "scene kept from the last render");
            return Ok(scene.clone());
        }
        self.scene = None;
        let scene = load()?;
        self.scene = Some((key, scene.clone()));
        Ok(scene)
    }

    /// Actors for `a`: the running ones when `a` asks for the same shape (workers,
    /// threads, budget), else new ones (the old are stopped first).
    pub fn actors(&mut self, a: &RenderArgs) -> Result<&Actors> {
        let cache_hosts = self.cache_hosts || crate::embedded::wants_cache_hosts(a)?;
        let shape = ActorsShape::of(a, a.workers, cache_hosts);
        if let Some(old) = self.actors.take_if(|running| *running.shape() != shape) {
            old.stop();
        }
        let actors = match self.actors.take() {
            Some(running) => running,
            None => Actors::start(shape, true)?,
        };
        Ok(self.actors.insert(actors))
    }
}

impl Drop for WarmProcess {
    fn drop(&mut self) {
        if let Some(actors) = self.actors.take() {
            actors.stop();
        }
    }
}
