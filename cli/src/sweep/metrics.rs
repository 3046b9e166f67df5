//! How far a setting's image is from the exact one: RMSE on the 8-bit sRGB values a
//! viewer sees, scaled to [0, 1] (the kind of RMS error Little 2011's Table 5.1
//! reports, not shown to be the thesis's definition: its images, colour handling and
//! scale are not reproduced), RMSE on linear radiance (what the renderer computes,
//! unclamped), PSNR, and NVIDIA's FLIP (a perceptual difference, mean over pixels in
//! [0, 1]; NVIDIA's reference C++ through the `nv-flip` crate).

use anyhow::{Result, bail};

/// An image as the sweep compares it.
#[derive(Clone, Debug, PartialEq)]
pub struct Picture {
    pub width: u32,
    pub height: u32,
    /// 8-bit sRGB, RGB, row-major: what the PNG holds.
    pub srgb8: Vec<u8>,
    /// Linear radiance, RGB, row-major.
    pub linear: Vec<f32>,
}

impl Picture {
    /// Checks the buffers' lengths against the size, so the metrics can zip them.
    pub fn new(width: u32, height: u32, srgb8: Vec<u8>, linear: Vec<f32>) -> Result<Picture> {
        let n = width as usize * height as usize * 3;
        if srgb8.len() != n || linear.len() != n {
            bail!(
                "a {width}x{height} image needs {n} RGB values, got {} sRGB and {} linear",
                srgb8.len(),
                linear.len()
            );
        }
        Ok(Picture {
            width,
            height,
            srgb8,
            linear,
        })
    }
}

/// The differences of `test` from `reference`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Errors {
    /// RMSE of the 8-bit sRGB values scaled to [0, 1], over all pixels and channels.
    pub rmse: f64,
    /// RMSE of linear radiance, over all pixels and channels.
    pub rmse_linear: f64,
    /// 20 log10(1 / rmse), dB; infinite for identical images.
    pub psnr: f64,
    /// Mean FLIP error (LDR FLIP on the sRGB images, 67 pixels per degree).
    pub flip: f64,
}

/// Compare `test` with `reference` (same size, or an error).
pub fn compare(reference: &Picture, test: &Picture) -> Result<Errors> {
    if (reference.width, reference.height) != (test.width, test.height) {
        bail!(
            "image size {}x{} differs from the exact image's {}x{}",
            test.width,
            test.height,
            reference.width,
            reference.height
        );
    }
    let rmse = rmse_srgb8(&reference.srgb8, &test.srgb8);
    Ok(Errors {
        rmse,
        rmse_linear: rmse_linear(&reference.linear, &test.linear),
        psnr: psnr(rmse),
        flip: flip(reference, test),
    })
}

/// RMSE of 8-bit values scaled to [0, 1].
pub fn rmse_srgb8(a: &[u8], b: &[u8]) -> f64 {
    rmse_by(
        a.iter()
            .zip(b)
            .map(|(x, y)| (f64::from(*x) - f64::from(*y)) / 255.0),
        a.len(),
    )
}

/// RMSE of linear values. Non-finite values never reach an image (the film drops them).
pub fn rmse_linear(a: &[f32], b: &[f32]) -> f64 {
    rmse_by(
        a.iter().zip(b).map(|(x, y)| f64::from(*x) - f64::from(*y)),
        a.len(),
    )
}

fn rmse_by(diffs: impl Iterator<Item = f64>, n: usize) -> f64 {
    if n == 0 {
        return 0.0;
    }
    (diffs.map(|d| d * d).sum::<f64>() / n as f64).sqrt()
}

/// PSNR in dB for values in [0, 1]: infinite when nothing differs.
pub fn psnr(rmse: f64) -> f64 {
    if rmse == 0.0 {
        f64::INFINITY
    } else {
        -20.0 * rmse.log10()
    }
}

/// Mean LDR FLIP of `test` against `reference` (same size). Identical images give 0
/// exactly without calling into FLIP.
pub fn flip(reference: &Picture, test: &Picture) -> f64 {
    if reference.srgb8 == test.srgb8 {
        return 0.0;
    }
    let r = nv_flip::FlipImageRgb8::with_data(reference.width, reference.height, &reference.srgb8);
    let t = nv_flip::FlipImageRgb8::with_data(test.width, test.height, &test.srgb8);
    let map = nv_flip::flip(r, t, nv_flip::DEFAULT_PIXELS_PER_DEGREE);
    f64::from(nv_flip::FlipPool::from_image(&map).mean())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pic(w: u32, h: u32, srgb8: Vec<u8>) -> Picture {
        let linear = srgb8.iter().map(|v| f32::from(*v) / 255.0).collect();
        Picture::new(w, h, srgb8, linear).unwrap()
    }

    #[test]
    fn identical_images_have_no_error() {
        let a = pic(4, 3, (0..36).map(|i| (i * 7) as u8).collect());
        let e = compare(&a, &a).unwrap();
        assert_eq!(e.rmse, 0.0);
        assert_eq!(e.rmse_linear, 0.0);
        assert_eq!(e.psnr, f64::INFINITY);
        assert_eq!(e.flip, 0.0);
    }

    #[test]
    fn known_small_case() {
        // Two pixels: one channel differs by 255 (1.0), five agree: RMSE = sqrt(1/6).
        let a = pic(2, 1, vec![0, 0, 0, 10, 20, 30]);
        let b = pic(2, 1, vec![255, 0, 0, 10, 20, 30]);
        let e = compare(&a, &b).unwrap();
        assert!((e.rmse - (1.0f64 / 6.0).sqrt()).abs() < 1e-12, "{e:?}");
        assert!((e.psnr - 10.0 * 6f64.log10()).abs() < 1e-9, "{e:?}");
        assert!(
            (e.rmse_linear - (1.0f64 / 6.0).sqrt()).abs() < 1e-7,
            "{e:?}"
        );
        assert_eq!(rmse_linear(&[1.0, 2.0], &[1.0, 4.0]), 2f64.sqrt());
        assert_eq!(psnr(0.1), 20.0);
    }

    #[test]
    fn flip_itself_gives_identical_images_zero() {
        // `flip` answers identical images without FLIP; FLIP agrees.
        let data: Vec<u8> = (0..16 * 16 * 3).map(|i| (i * 37 % 256) as u8).collect();
        let r = nv_flip::FlipImageRgb8::with_data(16, 16, &data);
        let t = nv_flip::FlipImageRgb8::with_data(16, 16, &data);
        let map = nv_flip::flip(r, t, nv_flip::DEFAULT_PIXELS_PER_DEGREE);
        assert_eq!(nv_flip::FlipPool::from_image(&map).mean(), 0.0);
    }

    #[test]
    fn flip_sees_a_difference() {
        let a = pic(16, 16, vec![128; 16 * 16 * 3]);
        let mut data = vec![128; 16 * 16 * 3];
        for v in &mut data[..16 * 8 * 3] {
            *v = 255;
        }
        let b = pic(16, 16, data);
        let e = compare(&a, &b).unwrap();
        assert!(e.flip > 0.0 && e.flip <= 1.0, "{e:?}");
        // Further from the reference, larger error.
        let c = pic(16, 16, vec![255; 16 * 16 * 3]);
        assert!(flip(&a, &c) > e.flip, "{} vs {}", flip(&a, &c), e.flip);
    }

    #[test]
    fn sizes_must_match() {
        let a = pic(2, 1, vec![0; 6]);
        let b = pic(1, 2, vec![0; 6]);
        assert!(compare(&a, &b).is_err());
        assert!(Picture::new(2, 2, vec![0; 3], vec![0.0; 12]).is_err());
    }
}
