//! The single-process driver: deals tiles to a thread pool and runs every ray of a tile
//! through the integrator's steps against one BVH. Tiles accumulate into their own
//! fixed-point buffers and merge into the film with integer additions, so the image is
//! identical for any thread count.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use glam::Vec3;
use rayon::prelude::*;

use crate::aov::{AOV_WORDS, FirstHit, add_aov_sums};
use crate::film::{Film, add_sums, to_fixed_clamped};
use crate::integrator::{Integrator, RayKind, RayState, Sink};
use crate::tiles::{Tile, TileGrid};
use crate::trace::Trace;

/// Rays traced, by kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayCounts(pub [u64; RayKind::COUNT]);

impl RayCounts {
    pub fn total(&self) -> u64 {
        self.0.iter().sum()
    }
    pub fn get(&self, k: RayKind) -> u64 {
        self.0[k as usize]
    }
}

#[derive(Clone, Debug)]
pub struct RenderOutput {
    pub film: Film,
    pub rays: RayCounts,
    pub render_time: Duration,
}

struct TileSink {
    tile: Tile,
    width: u32,
    sums: Vec<[i64; 3]>,
    nonfinite: u64,
    clamped: u64,
    clamped_indirect: u64,
    /// AOV sums by pixel of the tile; empty when the job records no first hits.
    aovs: Vec<[i64; AOV_WORDS]>,
    stack: Vec<RayState>,
}

impl TileSink {
    /// `pixel`'s index in the tile's buffers, if it is in the tile.
    #[inline]
    fn local(&self, pixel: u32) -> Option<usize> {
        let (x, y) = (pixel % self.width, pixel / self.width);
        let (lx, ly) = (x.wrapping_sub(self.tile.x0), y.wrapping_sub(self.tile.y0));
        (lx < self.tile.w && ly < self.tile.h).then(|| (ly * self.tile.w + lx) as usize)
    }
}

impl Sink for TileSink {
    fn contribute(&mut self, pixel: u32, value: Vec3) {
        let Some(i) = self.local(pixel) else {
            return;
        };
        match to_fixed_clamped(value) {
            Some((f, clamped)) => {
                self.clamped += u64::from(clamped);
                add_sums(&mut self.sums[i], f);
            }
            None => self.nonfinite += 1,
        }
    }

    fn spawn(&mut self, ray: RayState) {
        self.stack.push(ray);
    }

    fn clamped_indirect(&mut self) {
        self.clamped_indirect += 1;
    }

    fn first_hit(&mut self, pixel: u32, hit: &FirstHit) {
        if let (Some(i), Some(f)) = (self.local(pixel), hit.to_fixed())
            && let Some(s) = self.aovs.get_mut(i)
        {
            add_aov_sums(s, &f);
        }
    }
}

/// Render the whole image with `threads` worker threads (0 = all cores).
/// `progress` is called with (tiles done, tiles total) after every tile.
pub fn render(
    integrator: &Integrator<'_>,
    geometry: &dyn Trace,
    threads: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<RenderOutput, rayon::ThreadPoolBuildError> {
    render_cancellable(
        integrator,
        geometry,
        threads,
        progress,
        &AtomicBool::new(false),
    )
}

/// [`render`] with a cooperative cancel flag: once `cancel` is set, tiles not yet started
/// are skipped (a tile already being traced finishes), so the call returns soon with an
/// incomplete film. The caller checks `cancel` afterwards to know whether the film is whole.
pub fn render_cancellable(
    integrator: &Integrator<'_>,
    geometry: &dyn Trace,
    threads: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<RenderOutput, rayon::ThreadPoolBuildError> {
    let all = 0..integrator.settings.spp.max(1);
    render_passes(
        integrator,
        geometry,
        threads,
        std::slice::from_ref(&all),
        None,
        progress,
        &|_, _| {},
        cancel,
    )
}

/// [`render_cancellable`] in progressive passes (`crate::passes`): pass `k` traces
/// samples `passes[k]` of every pixel, and `on_pass(film, k)` is called with the image
/// of passes `0..=k` once pass `k` is complete (before the next starts). `progress` is
/// called with (tiles done in this pass, tiles) after every tile. The final film is the
/// same bits as one pass of every sample: sums are fixed-point integers, and each
/// sample's random numbers are keyed by pixel and sample index.
///
/// With a `noise_threshold` (adaptive sampling, `crate::adaptive`), a tile whose error
/// after a pass is below it takes no later pass, and its pixels keep the samples they
/// stopped at in the film: the same decisions, from the same integer sums, as the
/// coordinator's for a job on workers.
#[allow(clippy::too_many_arguments)]
pub fn render_passes(
    integrator: &Integrator<'_>,
    geometry: &dyn Trace,
    threads: usize,
    passes: &[std::ops::Range<u32>],
    noise_threshold: Option<f32>,
    progress: &(dyn Fn(usize, usize) + Sync),
    on_pass: &(dyn Fn(&Film, usize) + Sync),
    cancel: &AtomicBool,
) -> Result<RenderOutput, rayon::ThreadPoolBuildError> {
    let s = &integrator.settings;
    let (width, height) = (s.width, s.height);
    let tiles: Vec<Tile> = TileGrid::image(width, height).iter().collect();
    let film = Mutex::new(Film::with_aovs(width, height, s.aovs));
    let records_hits = s.aovs.records_hits();
    let counts: Vec<AtomicU64> = (0..RayKind::COUNT).map(|_| AtomicU64::new(0)).collect();
    let done = AtomicU64::new(0);
    // Tiles adaptive sampling stopped: written at a pass's end, read in later passes.
    let stopped: Vec<AtomicBool> = tiles.iter().map(|_| AtomicBool::new(false)).collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let start = Instant::now();
    for (k, samples) in passes.iter().enumerate() {
        done.store(0, Ordering::Relaxed);
        let decides = noise_threshold
            .filter(|_| crate::adaptive::decides_after(samples, k + 1 == passes.len()));
        pool.install(|| {
            tiles.par_iter().enumerate().for_each(|(t, tile)| {
                if cancel.load(Ordering::Relaxed) {
                    return;
                }
                if stopped[t].load(Ordering::Relaxed) {
                    let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                    progress(d as usize, tiles.len());
                    return;
                }
                let _span = tracing::trace_span!("tile", x = tile.x0, y = tile.y0).entered();
                let (sink, local) = trace_tile(integrator, geometry, tile, samples, records_hits);
                for (c, n) in counts.iter().zip(local) {
                    c.fetch_add(n, Ordering::Relaxed);
                }
                let mut f = dray_sync::lock(&film);
                if add_tile(&mut f, &sink, samples, decides) {
                    stopped[t].store(true, Ordering::Relaxed);
                }
                drop(f);
                let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                progress(d as usize, tiles.len());
            });
        });
        if cancel.load(Ordering::Relaxed) {
            break;
        }
        on_pass(&dray_sync::lock(&film), k);
    }
    let render_time = start.elapsed();
    let mut rays = RayCounts::default();
    for (i, c) in counts.iter().enumerate() {
        rays.0[i] = c.load(Ordering::Relaxed);
    }
    Ok(RenderOutput {
        film: dray_sync::into_inner(film),
        rays,
        render_time,
    })
}

/// Traces every camera ray of samples `samples` of `tile`'s pixels, each ray's tree
/// depth first, into a sink of the tile's own: its sums, and the rays traced by kind.
fn trace_tile(
    integrator: &Integrator<'_>,
    geometry: &dyn Trace,
    tile: &Tile,
    samples: &std::ops::Range<u32>,
    records_hits: bool,
) -> (TileSink, [u64; RayKind::COUNT]) {
    let mut sink = TileSink {
        tile: *tile,
        width: integrator.settings.width,
        sums: vec![[0; 3]; (tile.w * tile.h) as usize],
        nonfinite: 0,
        clamped: 0,
        clamped_indirect: 0,
        aovs: if records_hits {
            vec![[0; AOV_WORDS]; (tile.w * tile.h) as usize]
        } else {
            Vec::new()
        },
        stack: Vec::with_capacity(64),
    };
    let mut local = [0u64; RayKind::COUNT];
    for y in tile.y0..tile.y0 + tile.h {
        for x in tile.x0..tile.x0 + tile.w {
            for sample in samples.clone() {
                sink.stack.push(integrator.camera_ray_xy(x, y, sample));
                while let Some(ray) = sink.stack.pop() {
                    local[ray.kind as usize] += 1;
                    if ray.kind.is_occlusion() {
                        let occ = integrator.occluded(geometry, &ray);
                        integrator.shadow_result(&ray, occ, &mut sink);
                    } else {
                        match integrator.intersect(geometry, &ray) {
                            Some(hit) => integrator.shade_hit(&ray, &hit, &mut sink),
                            None => integrator.shade_miss(&ray, &mut sink),
                        }
                    }
                }
            }
        }
    }
    (sink, local)
}

/// Adds a traced tile's sums to the film. With `decides` (the pass after which adaptive
/// sampling decides, and its threshold), first decides whether the tile stops, from the
/// same integer sums before and after the pass as the coordinator's decision; a tile that
/// stops has its pixels' stop recorded at the pass's end. Returns whether it stopped.
fn add_tile(
    f: &mut Film,
    sink: &TileSink,
    samples: &std::ops::Range<u32>,
    decides: Option<f32>,
) -> bool {
    let (tile, width) = (sink.tile, sink.width);
    let mut stopped = false;
    if let Some(threshold) = decides {
        let _span = tracing::trace_span!("adaptive_decision").entered();
        let pixels = (0..tile.h).flat_map(|ly| {
            (0..tile.w).map(move |lx| (ly * tile.w + lx, (tile.y0 + ly) * width + tile.x0 + lx))
        });
        let error = crate::adaptive::tile_error(
            samples,
            pixels.clone().map(|(i, p)| {
                let before = f.sum_fixed(p);
                let mut after = before;
                add_sums(&mut after, sink.sums[i as usize]);
                (before, after)
            }),
        );
        if crate::adaptive::stops(error, threshold) {
            stopped = true;
            for (_, p) in pixels {
                f.set_stop(p, samples.end);
            }
        }
    }
    for ly in 0..tile.h {
        for lx in 0..tile.w {
            let pixel = (tile.y0 + ly) * width + tile.x0 + lx;
            f.add_fixed(pixel, sink.sums[(ly * tile.w + lx) as usize]);
        }
    }
    f.nonfinite += sink.nonfinite;
    f.clamped += sink.clamped;
    f.clamped_indirect += sink.clamped_indirect;
    if let Some(a) = f.aovs.as_mut() {
        for (i, s) in sink.aovs.iter().enumerate() {
            let (lx, ly) = (i as u32 % tile.w, i as u32 / tile.w);
            a.add_fixed((tile.y0 + ly) * width + tile.x0 + lx, s);
        }
    }
    stopped
}
