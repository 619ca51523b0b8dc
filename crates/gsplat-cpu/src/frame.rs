//! Rendered images and their conversion to masks and 8-bit pictures.

use image::{Rgb, RgbImage};

use crate::Error;

/// Opacity above which a rendered pixel counts as the object in the J/F masks (the PGRD
/// evaluation thresholds renders at 0.1).
pub const MASK_THRESHOLD: f32 = 0.1;

/// A rendered image: row-major, `[y][x]`, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Colour, channel-interleaved `[y][x][c]`, `3 * width * height` values (the layout of the
    /// `metrics::image` functions).
    pub rgb: Vec<f32>,
    /// Accumulated opacity `1 − transmittance` per pixel, in `[0, 1)`.
    pub alpha: Vec<f32>,
    /// Expected camera depth of what the pixel shows, metres: `Σ wᵢ zᵢ / Σ wᵢ` over the
    /// composited splats (weights `wᵢ = αᵢ Tᵢ`, `zᵢ` the camera z of the splat's centre); 0
    /// where nothing was drawn.
    pub depth: Vec<f32>,
}

impl Image {
    /// A transparent black image (alpha 0, depth 0).
    pub fn blank(width: usize, height: usize) -> Self {
        let n = width * height;
        Image {
            width,
            height,
            rgb: vec![0.0; 3 * n],
            alpha: vec![0.0; n],
            depth: vec![0.0; n],
        }
    }

    /// Index of pixel `(x, y)` (column, row) into `alpha` and `depth`; `3 *` that into `rgb`.
    pub fn index(&self, x: usize, y: usize) -> usize {
        y * self.width + x
    }

    /// Colour of pixel `(x, y)`.
    pub fn pixel(&self, x: usize, y: usize) -> [f32; 3] {
        let k = 3 * self.index(x, y);
        [self.rgb[k], self.rgb[k + 1], self.rgb[k + 2]]
    }

    /// Foreground mask `alpha > threshold`, row-major (for J and F use [`MASK_THRESHOLD`]).
    pub fn mask(&self, threshold: f32) -> Vec<bool> {
        self.alpha.iter().map(|&a| a > threshold).collect()
    }

    /// Colour as 8-bit RGB: each channel clamped to `[0, 1]`, scaled by 255 and rounded
    /// (non-finite values become 0).
    pub fn to_rgb8(&self) -> RgbImage {
        let to8 = |v: f32| {
            if v.is_finite() {
                (v.clamp(0.0, 1.0) * 255.0).round() as u8
            } else {
                0
            }
        };
        let mut out = RgbImage::new(self.width as u32, self.height as u32);
        for (k, px) in out.pixels_mut().enumerate() {
            *px = Rgb([
                to8(self.rgb[3 * k]),
                to8(self.rgb[3 * k + 1]),
                to8(self.rgb[3 * k + 2]),
            ]);
        }
        out
    }

    /// The mask as a black-on-white 8-bit picture (object black), for looking at J/F inputs.
    pub fn mask_rgb8(&self, threshold: f32) -> RgbImage {
        let mut out = RgbImage::from_pixel(self.width as u32, self.height as u32, Rgb([255; 3]));
        for (px, &a) in out.pixels_mut().zip(&self.alpha) {
            if a > threshold {
                *px = Rgb([0; 3]);
            }
        }
        out
    }

    /// Checks that `other` has this image's size.
    ///
    /// # Errors
    /// [`Error::ImageSize`] when the sizes differ.
    pub fn check_same_size(&self, other: &Image) -> Result<(), Error> {
        if (self.width, self.height) != (other.width, other.height) {
            return Err(Error::ImageSize(format!(
                "{} x {} vs {} x {}",
                self.width, self.height, other.width, other.height
            )));
        }
        Ok(())
    }
}
