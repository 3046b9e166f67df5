//! A running job's film: the exact fixed-point pixel sums (and AOV sums) the workers
//! report, and the pass images made from them. Sums are added with integer arithmetic
//! into one [`Film`]: addition is associative, so the image does not depend on which
//! worker reported what, or in which order. Only this type writes the film; the job
//! says which tile is complete, cleared or stopped, and the film does the pixels.
//!
//! **Pass images.** The film as the current pass started (the previous pass's image) is
//! the base a tile traced again goes back to; the image after the current pass is built
//! a tile at a time, each tile's pixels copied in when its credit of the pass is all
//! back (they are final for the pass then: by the workers' contract, [`super::report`],
//! no contribution of the pass comes after its credit). When the pass ends every tile
//! is in it, and it becomes the pass image without a copy of the film: a copy of a whole
//! film (50 MB at 1080p) inside the report that ends a pass would stall every report of
//! the job behind it.

use std::sync::Arc;

use dray_core::aov::{AOV_WORDS, AovSet};
use dray_core::film::Film;
use dray_proto::v1::{ReportContributionsRequest, Tile};
use tonic::Status;

use crate::store::CommittedTile;

/// The film of a job on workers, and its pass images.
#[derive(Debug)]
pub struct JobFilm {
    film: Film,
    /// The film as the current pass started: None in the first pass (zero).
    pass_base: Option<Arc<Film>>,
    /// The image after the current pass, being built; None in the last pass (no image
    /// follows it).
    pass_next: Option<Film>,
    /// Pixels copied into pass images so far (what a report may cost beyond its own
    /// sums; tests hold it to the tiles a report finishes).
    pass_copied: u64,
}

impl JobFilm {
    /// A zero film of `width` x `height` with `aovs`, and the next pass image when the
    /// job has more than one pass.
    pub fn new(width: u32, height: u32, aovs: AovSet, passes: u32) -> JobFilm {
        JobFilm {
            film: Film::with_aovs(width, height, aovs),
            pass_base: None,
            pass_next: (passes > 1).then(|| Film::with_aovs(width, height, aovs)),
            pass_copied: 0,
        }
    }

    /// The film as it is now.
    pub fn film(&self) -> &Film {
        &self.film
    }

    /// The film as the current pass started (None in the first pass).
    pub fn pass_base(&self) -> Option<&Film> {
        self.pass_base.as_deref()
    }

    /// Pixels copied into pass images so far.
    pub fn pass_copied(&self) -> u64 {
        self.pass_copied
    }

    /// The finished film, with the job's counts of non-finite and clamped
    /// contributions.
    pub fn into_film(self, nonfinite: u64, clamped: u64, clamped_indirect: u64) -> Film {
        let mut film = self.film;
        film.nonfinite = nonfinite;
        film.clamped = clamped;
        film.clamped_indirect = clamped_indirect;
        film
    }

    /// A report's pixel sums may be added: three per pixel, every pixel inside the film,
    /// none negative; its AOV sums only for a film with AOVs, eight words per pixel,
    /// every pixel inside, and the words that cannot be negative (albedo, depth, hits)
    /// not negative.
    pub fn check(&self, r: &ReportContributionsRequest) -> Result<(), Status> {
        if r.sums.len() != 3 * r.pixels.len() {
            return Err(Status::invalid_argument(format!(
                "sums: {} values for {} pixels (three per pixel expected)",
                r.sums.len(),
                r.pixels.len()
            )));
        }
        self.inside("pixels", &r.pixels)?;
        // Contributions are non-negative (`dray_core::film::to_fixed`) and every sum of
        // them saturates, which is what makes the film's sums independent of the order
        // reports arrive in; a negative value can only come from a broken or hostile
        // worker.
        if let Some(i) = r.sums.iter().position(|&v| v < 0) {
            return Err(Status::invalid_argument(format!(
                "sums: {} for pixel {} is negative (contributions never are)",
                r.sums[i],
                r.pixels[i / 3]
            )));
        }
        self.check_aovs(r)
    }

    fn check_aovs(&self, r: &ReportContributionsRequest) -> Result<(), Status> {
        if r.aov_pixels.is_empty() && r.aov_sums.is_empty() {
            return Ok(());
        }
        if self.film.aovs.is_none() {
            return Err(Status::invalid_argument(format!(
                "aov_pixels: job {:?} writes no AOVs",
                r.job_id
            )));
        }
        if r.aov_sums.len() != AOV_WORDS * r.aov_pixels.len() {
            return Err(Status::invalid_argument(format!(
                "aov_sums: {} values for {} pixels ({AOV_WORDS} per pixel expected)",
                r.aov_sums.len(),
                r.aov_pixels.len()
            )));
        }
        self.inside("aov_pixels", &r.aov_pixels)?;
        for (i, v) in r.aov_sums.chunks_exact(AOV_WORDS).enumerate() {
            if [0, 1, 2, 6, 7].iter().any(|&w| v[w] < 0) {
                return Err(Status::invalid_argument(format!(
                    "aov_sums: pixel {}'s albedo, depth or hit count is negative",
                    r.aov_pixels[i]
                )));
            }
        }
        Ok(())
    }

    /// Every pixel of `pixels` (field `field`) lies inside the film.
    fn inside(&self, field: &str, pixels: &[u32]) -> Result<(), Status> {
        let npix = u64::from(self.film.width) * u64::from(self.film.height);
        match pixels.iter().find(|&&p| u64::from(p) >= npix) {
            Some(p) => Err(Status::invalid_argument(format!(
                "{field}: {p} is outside the {}x{} image",
                self.film.width, self.film.height
            ))),
            None => Ok(()),
        }
    }

    /// Add a report's sums (which [`JobFilm::check`] accepted).
    pub fn add(&mut self, r: &ReportContributionsRequest) {
        self.film.add_fixed_run(&r.pixels, &r.sums);
        if let Some(a) = self.film.aovs.as_mut() {
            for (&p, v) in r.aov_pixels.iter().zip(r.aov_sums.chunks_exact(AOV_WORDS)) {
                a.add_fixed(p, &std::array::from_fn(|w| v[w]));
            }
        }
    }

    /// The pixels of tile `x`, clipped to the film, row by row.
    fn pixels(&self, x: &Tile) -> impl Iterator<Item = u32> + Clone + use<> {
        let (w, h) = (self.film.width, self.film.height);
        let (x0, x1) = (x.x0, x.x0.saturating_add(x.width).min(w));
        (x.y0..x.y0.saturating_add(x.height).min(h))
            .flat_map(move |y| (x0..x1).map(move |xx| y * w + xx))
    }

    /// Whether a tile taken back from the job store fits tile `x`: one sum per pixel,
    /// and AOV sums exactly when the film has AOVs.
    pub fn fits(&self, x: &Tile, c: &CommittedTile) -> bool {
        let n = u64::from(x.width) * u64::from(x.height);
        c.sums.len() as u64 == n
            && c.aovs.as_ref().map(|a| a.len() as u64) == self.film.aovs.as_ref().map(|_| n)
    }

    /// Put back the sums of tile `x` committed before a restart (which
    /// [`JobFilm::fits`]), and the samples its pixels stopped at, if adaptive sampling
    /// stopped it. Returns its pixel count.
    pub fn keep(&mut self, x: &Tile, c: CommittedTile) -> u64 {
        let pixels = (x.y0..x.y0 + x.height)
            .flat_map(|y| (x.x0..x.x0 + x.width).map(move |xx| (y, xx)))
            .map(|(y, xx)| y * self.film.width + xx)
            .collect::<Vec<u32>>();
        for (&p, s) in pixels.iter().zip(c.sums) {
            self.film.add_fixed(p, s);
        }
        if let (Some(film), Some(aovs)) = (self.film.aovs.as_mut(), c.aovs) {
            for (&p, v) in pixels.iter().zip(aovs) {
                film.add_fixed(p, &v);
            }
        }
        if let Some(n) = c.stopped_at {
            for &p in &pixels {
                self.film.set_stop(p, n);
            }
        }
        pixels.len() as u64
    }

    /// Tile `x` as the job store keeps it once complete: its exact sums, AOV sums, and
    /// the samples it stopped at (a stopped tile's pixels all stopped at the same count).
    pub fn committed(&self, t: u32, x: &Tile, passes: u32) -> CommittedTile {
        let film = &self.film;
        let pixels = (x.y0..x.y0 + x.height)
            .flat_map(|y| (x.x0..x.x0 + x.width).map(move |xx| y * film.width + xx));
        let sums = pixels.clone().map(|p| film.sum_fixed(p)).collect();
        let aovs = film
            .aovs
            .as_ref()
            .map(|a| pixels.clone().map(|p| a.sum_fixed(p)).collect());
        let stopped_at = film
            .stops()
            .and_then(|s| s.get((x.y0 * film.width + x.x0) as usize))
            .copied()
            .filter(|&n| n > 0);
        CommittedTile {
            tile: t,
            sums,
            passes: Some(passes),
            aovs,
            stopped_at,
        }
    }

    /// Adaptive sampling's view of tile `x`: each pixel's sums before the current pass
    /// (zero in the first) and now, in order.
    pub fn tile_sums(&self, x: &Tile) -> impl Iterator<Item = ([i64; 3], [i64; 3])> + '_ {
        let base = self.pass_base.as_deref();
        self.pixels(x).map(move |p| {
            (
                base.map_or([0; 3], |b| b.sum_fixed(p)),
                self.film.sum_fixed(p),
            )
        })
    }

    /// Tile `x`'s pixels stop at `samples` (adaptive sampling); returns how many.
    pub fn stop_tile(&mut self, x: &Tile, samples: u32) -> u64 {
        let mut n = 0u64;
        for p in self.pixels(x) {
            self.film.set_stop(p, samples);
            n += 1;
        }
        n
    }

    /// Set every pixel of image tile `x` back to what it was when the current pass
    /// started (zero in the first), exactly: wrapping integer sums, adding the difference
    /// gives the base whatever the sum was.
    pub fn clear_tile(&mut self, x: &Tile) {
        for p in self.pixels(x) {
            self.film.set_pixel_from(p, self.pass_base.as_deref());
        }
    }

    /// Copy tile `x`'s pixels into the next pass image, if one is being built.
    pub fn copy_to_next(&mut self, x: &Tile) {
        let pixels = self.pixels(x);
        let Some(next) = self.pass_next.as_mut() else {
            return;
        };
        for p in pixels {
            // The next image's pixel may hold an older pass's sums (a reused buffer):
            // it is set, not added to.
            next.set_pixel_from(p, Some(&self.film));
            self.pass_copied += 1;
        }
    }

    /// The image the current pass ends with: the next pass image built tile by tile
    /// (there is always one before the last pass; a copy is the right image should
    /// there not be).
    pub fn take_pass_image(&mut self) -> Arc<Film> {
        Arc::new(self.pass_next.take().unwrap_or_else(|| self.film.clone()))
    }

    /// The film as it is now, as the base of a pass (a job taken back from the store).
    pub fn snapshot(&self) -> Arc<Film> {
        Arc::new(self.film.clone())
    }

    /// A new pass starts from `image`; unless it is the `last`, the next pass image is
    /// built again. Every tile of the next image is written before it is shown, so the
    /// image before this one can hold it when no reader has it any more (no new
    /// allocation, and its pages are already mapped).
    pub fn enter_pass(&mut self, image: Arc<Film>, last: bool) {
        let previous = self.pass_base.replace(image);
        self.pass_next = (!last).then(|| {
            let (w, h, aovs) = (self.film.width, self.film.height, self.film.aov_set());
            previous
                .and_then(|p| Arc::try_unwrap(p).ok())
                .filter(|f| (f.width, f.height, f.aov_set()) == (w, h, aovs))
                .unwrap_or_else(|| Film::with_aovs(w, h, aovs))
        });
    }

    /// Whether the film writes AOVs.
    pub fn has_aovs(&self) -> bool {
        self.film.aovs.is_some()
    }
}
