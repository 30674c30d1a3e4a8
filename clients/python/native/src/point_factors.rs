//! GTSAM's point priors and point betweens, written once over the library's dual numbers
//! (`factors::autodiff`): the residuals are linear, so automatic derivatives cost little, and
//! the Jacobians cannot disagree with the residuals. (The tests of the in-process package check
//! them on linear problems against numpy's least squares.)
//!
//! - `PriorFactorPoint2/3(key, p, noise)`: error `x − p`.
//! - `BetweenFactorPoint2/3(k1, k2, d, noise)`: error `(x₂ − x₁) − d` (GTSAM's `between` of
//!   points is their difference).

use factord::factors::autodiff::{AutoFactor, AutoResidual, Lifted, Real};
use factord::factors::Factor;

use crate::errors::FactordError;
use pyo3::PyResult;

/// `x − p` for a point of `D` coordinates.
#[derive(Debug)]
pub struct PriorPoint<const D: usize>(pub [f64; D]);

/// `(x₂ − x₁) − d` for points of `D` coordinates.
#[derive(Debug)]
pub struct BetweenPoint<const D: usize>(pub [f64; D]);

fn point<T: Copy, const D: usize>(v: &Lifted<T>) -> [T; D] {
    match v {
        Lifted::Point2(p) if D == 2 => std::array::from_fn(|i| p[i]),
        Lifted::Point3(p) if D == 3 => std::array::from_fn(|i| p[i]),
        _ => unreachable!("the kinds are checked when the factor enters a problem"),
    }
}

macro_rules! point_residuals {
    ($d:literal, $kind:literal, $prior:literal, $between:literal) => {
        impl AutoResidual<$d> for PriorPoint<$d> {
            const NAME: &'static str = $prior;
            const KINDS: &'static [&'static str] = &[$kind];
            const DIM: usize = $d;
            fn residual<T: Real>(&self, v: &[Lifted<T>], out: &mut [T]) {
                let x = point::<T, $d>(&v[0]);
                for i in 0..$d {
                    out[i] = x[i] - T::constant(self.0[i]);
                }
            }
        }

        impl AutoResidual<{ 2 * $d }> for BetweenPoint<$d> {
            const NAME: &'static str = $between;
            const KINDS: &'static [&'static str] = &[$kind, $kind];
            const DIM: usize = $d;
            fn residual<T: Real>(&self, v: &[Lifted<T>], out: &mut [T]) {
                let (a, b) = (point::<T, $d>(&v[0]), point::<T, $d>(&v[1]));
                for i in 0..$d {
                    out[i] = (b[i] - a[i]) - T::constant(self.0[i]);
                }
            }
        }
    };
}
point_residuals!(2, "point2", "prior_point2", "between_point2");
point_residuals!(3, "point3", "prior_point3", "between_point3");

/// The library factor of `residual` on `keys` (their count is the class's).
pub fn auto<const N: usize, R: AutoResidual<N>>(
    keys: Vec<factord::problem::Key>,
    residual: R,
) -> PyResult<Box<dyn Factor>> {
    AutoFactor::new(keys, residual)
        .map(|f| Box::new(f) as Box<dyn Factor>)
        .map_err(|e| FactordError::new_err(e.to_string()))
}
