//! Planar rotations. Angles are kept wrapped to (−π, π] so that errors compare like for like.

use std::f64::consts::PI;

/// Wraps an angle to (−π, π].
///
/// `rem_euclid` gives [0, 2π); shifting by π and back maps that onto [−π, π), and the one point
/// that lands on −π is moved to +π so the interval is closed on the right, as the course and g2o use.
pub fn wrap_angle(theta: f64) -> f64 {
    if (-PI..=PI).contains(&theta) && theta != -PI {
        return theta;
    }
    let wrapped = (theta + PI).rem_euclid(2.0 * PI) - PI;
    if wrapped <= -PI {
        PI
    } else {
        wrapped
    }
}

/// The 2×2 rotation matrix of `theta`, row-major `[[c, -s], [s, c]]`.
pub fn rotation(theta: f64) -> [[f64; 2]; 2] {
    let (s, c) = theta.sin_cos();
    [[c, -s], [s, c]]
}

/// [`rotation`] as an nalgebra matrix.
pub fn rotation_matrix_2d(theta: f64) -> nalgebra::Matrix2<f64> {
    let (s, c) = theta.sin_cos();
    nalgebra::Matrix2::new(c, -s, s, c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wraps_into_half_open_interval() {
        assert_eq!(wrap_angle(PI), PI);
        assert_eq!(wrap_angle(-PI), PI);
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(2.0 * PI + 0.1) - 0.1).abs() < 1e-12);
        assert!((wrap_angle(-2.0 * PI - 0.1) + 0.1).abs() < 1e-12);
        assert_eq!(wrap_angle(0.5), 0.5);
        for k in -50..50 {
            let w = wrap_angle(k as f64 * 0.77);
            assert!(w > -PI && w <= PI, "{w}");
        }
    }
}
