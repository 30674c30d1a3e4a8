//! Grayscale images sampled with bilinear interpolation, and the pinhole camera that looks at
//! them (direct / photometric bundle adjustment).

use nalgebra::{Matrix2x3, Vector2, Vector3};

/// An 8-bit (or photometrically corrected) grayscale image, row-major, intensities as `f32`.
#[derive(Clone, Debug, PartialEq)]
pub struct GrayImage {
    pub width: usize,
    pub height: usize,
    pixels: Vec<f32>,
}

/// A bilinear sample: the intensity and its derivatives along x (columns) and y (rows).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub value: f64,
    pub dx: f64,
    pub dy: f64,
}

impl GrayImage {
    /// `pixels` row-major, `width × height` of them.
    pub fn new(width: usize, height: usize, pixels: Vec<f32>) -> Option<Self> {
        (pixels.len() == width * height).then_some(Self {
            width,
            height,
            pixels,
        })
    }

    pub fn pixel(&self, x: usize, y: usize) -> f64 {
        f64::from(self.pixels[y * self.width + x])
    }

    /// Bilinear interpolation at (x, y) (x the column), with the exact derivatives of the
    /// interpolant inside its cell:
    ///
    /// ```text
    /// I = (1−a)(1−b) I00 + a(1−b) I10 + (1−a) b I01 + a b I11,   a = x − ⌊x⌋, b = y − ⌊y⌋
    /// ∂I/∂x = (1−b)(I10 − I00) + b (I11 − I01),   ∂I/∂y = (1−a)(I01 − I00) + a (I11 − I10)
    /// ```
    ///
    /// `None` unless the whole 2×2 neighbourhood is inside the image.
    pub fn sample(&self, x: f64, y: f64) -> Option<Sample> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (c, r) = (x0 as usize, y0 as usize);
        if c + 1 >= self.width || r + 1 >= self.height {
            return None;
        }
        let (a, b) = (x - x0, y - y0);
        let (i00, i10) = (self.pixel(c, r), self.pixel(c + 1, r));
        let (i01, i11) = (self.pixel(c, r + 1), self.pixel(c + 1, r + 1));
        Some(Sample {
            value: (1.0 - a) * (1.0 - b) * i00
                + a * (1.0 - b) * i10
                + (1.0 - a) * b * i01
                + a * b * i11,
            dx: (1.0 - b) * (i10 - i00) + b * (i11 - i01),
            dy: (1.0 - a) * (i01 - i00) + a * (i11 - i10),
        })
    }
}

/// Pinhole intrinsics without distortion: `u = fx X/Z + cx`, `v = fy Y/Z + cy`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    /// The pixel of camera-frame point `p` (no check that `p.z > 0`).
    pub fn project(&self, p: &Vector3<f64>) -> Vector2<f64> {
        Vector2::new(self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }

    /// ∂(u, v)/∂p at camera-frame point `p`.
    pub fn project_jacobian(&self, p: &Vector3<f64>) -> Matrix2x3<f64> {
        let iz = 1.0 / p.z;
        Matrix2x3::new(
            self.fx * iz,
            0.0,
            -self.fx * p.x * iz * iz,
            0.0,
            self.fy * iz,
            -self.fy * p.y * iz * iz,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_sample_interpolates_and_differentiates() {
        // I = 3x + 5y + 1 is reproduced exactly by bilinear interpolation.
        let (w, h) = (6, 4);
        let pixels = (0..h)
            .flat_map(|y| (0..w).map(move |x| (3 * x + 5 * y + 1) as f32))
            .collect();
        let image = GrayImage::new(w, h, pixels).unwrap();
        let s = image.sample(2.25, 1.5).unwrap();
        assert!((s.value - (3.0 * 2.25 + 5.0 * 1.5 + 1.0)).abs() < 1e-12);
        assert!((s.dx - 3.0).abs() < 1e-12 && (s.dy - 5.0).abs() < 1e-12);
        assert!(image.sample(4.99, 2.99).is_some());
        assert!(image.sample(5.0, 1.0).is_none());
        assert!(image.sample(-0.1, 1.0).is_none());
        assert!(image.sample(f64::NAN, 1.0).is_none());
        assert!(GrayImage::new(2, 2, vec![0.0; 3]).is_none());
    }
}
