//! Piecewise-constant distributions in one and two dimensions (pbrt's
//! `PiecewiseConstant1D` and `2D`): the importance sampler of an environment map.

use glam::Vec2;

/// A piecewise-constant density on [0, 1) with one cell per weight.
#[derive(Clone, Debug)]
pub struct Distribution1D {
    /// The weights (non-negative).
    func: Vec<f32>,
    /// Running integral, `cdf[0] = 0`, `cdf[n] = 1`.
    cdf: Vec<f32>,
    /// The integral of `func` over [0, 1) (mean weight).
    integral: f32,
}

impl Distribution1D {
    /// Weights must be finite and non-negative; all zero gives the uniform density.
    pub fn new(weights: &[f32]) -> Distribution1D {
        let n = weights.len().max(1);
        let func: Vec<f32> = if weights.is_empty() {
            vec![0.0]
        } else {
            weights
                .iter()
                .map(|w| if w.is_finite() { w.max(0.0) } else { 0.0 })
                .collect()
        };
        let mut acc = 0.0f64;
        let mut cdf = Vec::with_capacity(n + 1);
        cdf.push(0.0f64);
        for &w in &func {
            acc += f64::from(w) / n as f64;
            cdf.push(acc);
        }
        let integral = acc;
        let cdf = if integral > 0.0 {
            cdf.iter().map(|c| (c / integral) as f32).collect()
        } else {
            (0..=n).map(|i| i as f32 / n as f32).collect()
        };
        Distribution1D {
            func,
            cdf,
            integral: integral as f32,
        }
    }

    pub fn len(&self) -> usize {
        self.func.len()
    }

    pub fn is_empty(&self) -> bool {
        false
    }

    pub fn integral(&self) -> f32 {
        self.integral
    }

    /// The density at cell `i` (over [0, 1)).
    pub fn pdf(&self, i: usize) -> f32 {
        if self.integral > 0.0 {
            self.func.get(i).copied().unwrap_or(0.0) / self.integral
        } else {
            1.0
        }
    }

    /// A point in [0, 1) with this density from `u` in [0, 1), its density and cell.
    pub fn sample(&self, u: f32) -> (f32, f32, usize) {
        let n = self.func.len();
        // The last cell whose start is <= u, among cells of non-zero width.
        let i = (self.cdf.partition_point(|&c| c <= u).max(1) - 1).min(n - 1);
        let (c0, c1) = (self.cdf[i], self.cdf[i + 1]);
        let du = if c1 > c0 { (u - c0) / (c1 - c0) } else { 0.5 };
        let x = ((i as f32 + du.clamp(0.0, 1.0)) / n as f32).min(1.0 - f32::EPSILON / 2.0);
        (x, self.pdf(i), i)
    }
}

/// A piecewise-constant density on [0, 1)^2 over a `width` x `height` grid of weights
/// (row-major, row 0 at v = 0): a row chosen by its total, then a column in it.
#[derive(Clone, Debug)]
pub struct Distribution2D {
    rows: Vec<Distribution1D>,
    marginal: Distribution1D,
}

impl Distribution2D {
    pub fn new(weights: &[f32], width: usize, height: usize) -> Distribution2D {
        let rows: Vec<Distribution1D> = (0..height)
            .map(|y| Distribution1D::new(&weights[y * width..(y + 1) * width]))
            .collect();
        let marginal = Distribution1D::new(&rows.iter().map(|r| r.integral()).collect::<Vec<_>>());
        Distribution2D { rows, marginal }
    }

    /// A point with this density from `u`, and its density (over [0, 1)^2).
    pub fn sample(&self, u: Vec2) -> (Vec2, f32) {
        let (v, pv, y) = self.marginal.sample(u.y);
        let (x, pu, _) = self.rows[y].sample(u.x);
        (Vec2::new(x, v), pv * pu)
    }

    /// The density at `p` in [0, 1)^2.
    pub fn pdf(&self, p: Vec2) -> f32 {
        let h = self.rows.len();
        let y = ((p.y * h as f32) as usize).min(h - 1);
        let row = &self.rows[y];
        let x = ((p.x * row.len() as f32) as usize).min(row.len() - 1);
        self.marginal.pdf(y) * row.pdf(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_follow_the_weights_and_the_pdf_integrates_to_one() {
        let (w, h) = (7, 5);
        let weights: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 11) as f32).collect();
        let d = Distribution2D::new(&weights, w, h);
        // The pdf integrates to one over the grid.
        let total: f32 = (0..w * h)
            .map(|i| {
                let p = Vec2::new(
                    ((i % w) as f32 + 0.5) / w as f32,
                    ((i / w) as f32 + 0.5) / h as f32,
                );
                d.pdf(p) / (w * h) as f32
            })
            .sum();
        assert!((total - 1.0).abs() < 1e-5, "{total}");
        // Stratified samples land in each cell in proportion to its weight, and each
        // sample's pdf is the density of its cell.
        let sum: f32 = weights.iter().sum();
        let mut counts = vec![0u32; w * h];
        let n = 400;
        for i in 0..n {
            for j in 0..n {
                let u = Vec2::new((i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32);
                let (p, pdf) = d.sample(u);
                assert!(
                    (0.0..1.0).contains(&p.x) && (0.0..1.0).contains(&p.y),
                    "{p}"
                );
                assert!((pdf - d.pdf(p)).abs() <= 1e-4 * pdf, "{pdf} {}", d.pdf(p));
                let c = (p.y * h as f32) as usize * w + (p.x * w as f32) as usize;
                counts[c] += 1;
            }
        }
        for (c, &k) in counts.iter().enumerate() {
            // Exact density per cell; counts within one stratum of rows (n samples).
            let p = Vec2::new(
                ((c % w) as f32 + 0.5) / w as f32,
                ((c / w) as f32 + 0.5) / h as f32,
            );
            let share = weights[c] / sum;
            assert!((d.pdf(p) / (w * h) as f32 - share).abs() < 1e-6, "cell {c}");
            let want = share * (n * n) as f32;
            assert!(
                (k as f32 - want).abs() <= n as f32,
                "cell {c}: {k} vs {want}"
            );
            assert_eq!(k == 0, weights[c] == 0.0, "cell {c}");
        }
    }

    #[test]
    fn all_zero_weights_give_the_uniform_density() {
        let d = Distribution2D::new(&[0.0; 6], 3, 2);
        assert_eq!(d.pdf(Vec2::new(0.1, 0.9)), 1.0);
        let (p, pdf) = d.sample(Vec2::new(0.5, 0.25));
        assert_eq!(pdf, 1.0);
        assert!((p - Vec2::new(0.5, 0.25)).length() < 1e-6, "{p}");
    }
}
