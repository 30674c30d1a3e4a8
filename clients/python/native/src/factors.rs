//! Factors as Python objects with GTSAM's names and constructors. Each holds the library's factor
//! (shared, so a graph, its copies and every problem built from them use one instance), its
//! weight and kernel, and what GTSAM's `measured()` returns.

use std::sync::Arc;

use nalgebra::DMatrix;
use pyo3::prelude::*;

use factord::factors::{
    BearingRangeSe2, BearingSe2, BetweenSe2, BetweenSe3, Factor, GnssLeverArmSe3, GnssPositionSe3,
    PositionSe3Point3, PriorSe2, PriorSe3, RangeSe2, RangeSe2Point2, RangeSe3, RangeSe3Point3,
    ReprojectionSnavely, RobustKernel, SqrtInformation,
};
use factord::problem::Key;

use crate::arrays::fixed_vector_in;
use crate::custom::CustomFactor;
use crate::errors::{DimensionMismatch, InvalidNoiseModel};
use crate::keys::key_name;
use crate::noise::NoiseModel;
use crate::planar::{Pose2, Rot2};
use crate::point_factors::{auto, BetweenPoint, PriorPoint};
use crate::spatial::Pose3;

/// Declares [`FactorClass`] and [`factor_object`] from one list of the Python factor classes.
macro_rules! factor_classes {
    ($($name:ident),* $(,)?) => {
        /// Which Python class a factor is, to give it back as that class (`graph.at(i)`).
        #[derive(Clone, Copy, Debug, PartialEq, Eq)]
        pub enum FactorClass {
            $($name,)*
            /// Read from a file, of a type without a Python class of its own.
            Other,
        }

        /// The Python object for a factor a graph holds, of its own class.
        pub fn factor_object(py: Python<'_>, data: &Arc<FactorData>) -> PyResult<Py<PyAny>> {
            let base = NonlinearFactor { data: data.clone() };
            match data.class {
                $(FactorClass::$name => Ok(Py::new(py, PyClassInitializer::from(base).add_subclass($name))?.into_any()),)*
                FactorClass::Other => Ok(Py::new(py, base)?.into_any()),
            }
        }
    };
}

factor_classes!(
    PriorFactorPose2,
    BetweenFactorPose2,
    PriorFactorPose3,
    BetweenFactorPose3,
    BearingRangeFactor2D,
    RangeFactor2D,
    RangeFactorPose2,
    RangeFactor3D,
    RangeFactorPose3,
    BearingFactor2D,
    PriorFactorPoint2,
    PriorFactorPoint3,
    BetweenFactorPoint2,
    BetweenFactorPoint3,
    GPSFactor,
    GPSFactorArm,
    PoseToPointFactor3D,
    SnavelyReprojectionFactor,
    CustomFactor,
);

/// Everything a graph keeps of one factor.
#[derive(Debug)]
pub struct FactorData {
    pub factor: Arc<dyn Factor>,
    pub sqrt_information: SqrtInformation,
    pub robust: Option<RobustKernel>,
    pub noise: NoiseModel,
    pub label: String,
    pub class: FactorClass,
    /// What `measured()` returns (a `Pose2`, a `Rot2` and range, ...).
    pub measured: Option<Py<PyAny>>,
}

/// Whether the library's residual of this factor has GTSAM's `Pose3` tangent halves swapped
/// (library: translation first; GTSAM: rotation first).
fn swaps_pose3_halves(class: FactorClass) -> bool {
    matches!(
        class,
        FactorClass::PriorFactorPose3 | FactorClass::BetweenFactorPose3
    )
}

/// `information` with its two 3×3 halves swapped (6×6): GTSAM's Pose3 order ↔ the library's.
pub fn swap_pose3_information(information: &DMatrix<f64>) -> DMatrix<f64> {
    let perm = [3, 4, 5, 0, 1, 2];
    DMatrix::from_fn(6, 6, |r, c| information[(perm[r], perm[c])])
}

impl FactorData {
    /// Checks the noise model's dimension against the factor's and weighs it.
    pub fn new(
        factor: Box<dyn Factor>,
        noise: &NoiseModel,
        class: FactorClass,
        measured: Option<Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let names: Vec<String> = factor.keys().iter().map(|&k| key_name(k)).collect();
        let label = match class {
            FactorClass::Other => format!("{}({})", factor.name(), names.join(", ")),
            named => format!("{named:?}({})", names.join(", ")),
        };
        let dim = factor.residual_dim();
        if noise.size() != dim {
            return Err(DimensionMismatch::new_err(format!(
                "{label}: the noise model has dimension {}, the factor's error has {dim}",
                noise.size()
            )));
        }
        let information = if swaps_pose3_halves(class) {
            swap_pose3_information(&noise.information)
        } else {
            noise.information.clone()
        };
        let sqrt_information = SqrtInformation::from_information(&information)
            .map_err(|e| InvalidNoiseModel::new_err(format!("{label}: {e}")))?;
        Ok(Self {
            factor: Arc::from(factor),
            sqrt_information,
            robust: noise.robust,
            noise: noise.clone(),
            label,
            class,
            measured: measured.map(Bound::unbind),
        })
    }
}

/// Any factor (GTSAM: `NonlinearFactor`); the named classes below derive from it.
#[pyclass(module = "factord", name = "NonlinearFactor", subclass)]
pub struct NonlinearFactor {
    pub data: Arc<FactorData>,
}

#[pymethods]
impl NonlinearFactor {
    fn keys(&self) -> Vec<Key> {
        self.data.factor.keys().to_vec()
    }
    fn dim(&self) -> usize {
        self.data.factor.residual_dim()
    }
    fn size(&self) -> usize {
        self.data.factor.keys().len()
    }
    #[pyo3(name = "noiseModel")]
    fn noise_model(&self) -> NoiseModel {
        self.data.noise.clone()
    }
    fn measured(&self, py: Python<'_>) -> Py<PyAny> {
        match &self.data.measured {
            Some(m) => m.clone_ref(py),
            None => py.None(),
        }
    }
    /// `½ ρ(‖R e‖²)` at `values` (GTSAM's factor error).
    fn error(&self, values: &crate::values::Values) -> PyResult<f64> {
        crate::graph::factor_error(&self.data, values)
    }
    fn __repr__(&self) -> String {
        self.data.label.clone()
    }
}

type Made = (Box<dyn Factor>, Option<Py<PyAny>>);

fn base(
    py: Python<'_>,
    made: Made,
    noise: &NoiseModel,
    class: FactorClass,
) -> PyResult<NonlinearFactor> {
    let (factor, measured) = made;
    let data = FactorData::new(factor, noise, class, measured.map(|m| m.into_bound(py)))?;
    Ok(NonlinearFactor {
        data: Arc::new(data),
    })
}

/// A named factor class: `#[pyclass(extends=NonlinearFactor)]` with its constructor.
macro_rules! factor_class {
    ($name:ident, ($($arg:ident : $ty:ty),*), |$py:ident| $make:expr) => {
        #[pyclass(module = "factord", extends = NonlinearFactor)]
        pub struct $name;

        #[pymethods]
        impl $name {
            #[new]
            fn new($py: Python<'_>, $($arg: $ty,)* noise: &NoiseModel) -> PyResult<PyClassInitializer<Self>> {
                let made: Made = $make;
                Ok(PyClassInitializer::from(base($py, made, noise, FactorClass::$name)?).add_subclass($name))
            }
        }
    };
}

factor_class!(PriorFactorPose2, (key: Key, prior: Pose2), |py| (
    Box::new(PriorSe2::new(key, prior.inner)),
    Some(Py::new(py, prior)?.into_any())
));
factor_class!(BetweenFactorPose2, (key1: Key, key2: Key, measured: Pose2), |py| (
    Box::new(BetweenSe2::new(key1, key2, measured.inner)),
    Some(Py::new(py, measured)?.into_any())
));
factor_class!(PriorFactorPose3, (key: Key, prior: Pose3), |py| (
    Box::new(PriorSe3::new(key, prior.inner)),
    Some(Py::new(py, prior)?.into_any())
));
factor_class!(BetweenFactorPose3, (key1: Key, key2: Key, measured: Pose3), |py| (
    Box::new(BetweenSe3::new(key1, key2, measured.inner)),
    Some(Py::new(py, measured)?.into_any())
));
factor_class!(
    BearingRangeFactor2D,
    (pose_key: Key, point_key: Key, bearing: Rot2, range: f64),
    |py| (
        Box::new(BearingRangeSe2::new(pose_key, point_key, bearing.theta, range)),
        Some((Py::new(py, bearing)?, range).into_pyobject(py)?.into_any().unbind())
    )
);
factor_class!(RangeFactor2D, (pose_key: Key, point_key: Key, range: f64), |py| (
    Box::new(RangeSe2Point2::new(pose_key, point_key, range)),
    Some(range.into_pyobject(py)?.into_any().unbind())
));
factor_class!(RangeFactorPose2, (key1: Key, key2: Key, range: f64), |py| (
    Box::new(RangeSe2::new(key1, key2, range)),
    Some(range.into_pyobject(py)?.into_any().unbind())
));
factor_class!(RangeFactor3D, (pose_key: Key, point_key: Key, range: f64), |py| (
    Box::new(RangeSe3Point3::new(pose_key, point_key, range)),
    Some(range.into_pyobject(py)?.into_any().unbind())
));
factor_class!(RangeFactorPose3, (key1: Key, key2: Key, range: f64), |py| (
    Box::new(RangeSe3::new(key1, key2, range)),
    Some(range.into_pyobject(py)?.into_any().unbind())
));

factor_class!(
    BearingFactor2D,
    (pose_key: Key, point_key: Key, bearing: Rot2),
    |py| (
        Box::new(BearingSe2::new(pose_key, point_key, bearing.theta)),
        Some(Py::new(py, bearing)?.into_any())
    )
);

/// A point of `N` coordinates given to a factor's constructor.
fn point_in<const N: usize>(value: &Bound<'_, PyAny>, what: &str) -> PyResult<[f64; N]> {
    let v = fixed_vector_in(value, N, what)?;
    Ok(std::array::from_fn(|i| v[i]))
}

/// What `measured()` answers for a point: a copy (a caller's array may change afterwards).
fn copy_of(py: Python<'_>, point: &[f64]) -> PyResult<Py<PyAny>> {
    Ok(crate::arrays::vector_out(py, point)?.unbind())
}

factor_class!(PriorFactorPoint2, (key: Key, prior: Bound<'_, PyAny>), |py| {
    let p = point_in::<2>(&prior, "PriorFactorPoint2 prior")?;
    (auto(vec![key], PriorPoint(p))?, Some(copy_of(py, &p)?))
});
factor_class!(PriorFactorPoint3, (key: Key, prior: Bound<'_, PyAny>), |py| {
    let p = point_in::<3>(&prior, "PriorFactorPoint3 prior")?;
    (auto(vec![key], PriorPoint(p))?, Some(copy_of(py, &p)?))
});
factor_class!(BetweenFactorPoint2, (key1: Key, key2: Key, measured: Bound<'_, PyAny>), |py| {
    let d = point_in::<2>(&measured, "BetweenFactorPoint2 measured")?;
    (auto(vec![key1, key2], BetweenPoint(d))?, Some(copy_of(py, &d)?))
});
factor_class!(BetweenFactorPoint3, (key1: Key, key2: Key, measured: Bound<'_, PyAny>), |py| {
    let d = point_in::<3>(&measured, "BetweenFactorPoint3 measured")?;
    (auto(vec![key1, key2], BetweenPoint(d))?, Some(copy_of(py, &d)?))
});

factor_class!(GPSFactor, (key: Key, gps_in: Bound<'_, PyAny>), |py| {
    let p = point_in::<3>(&gps_in, "GPSFactor gpsIn")?;
    (Box::new(GnssPositionSe3::new(key, p.into())), Some(copy_of(py, &p)?))
});
factor_class!(
    GPSFactorArm,
    (key: Key, gps_in: Bound<'_, PyAny>, lever_arm: Bound<'_, PyAny>),
    |py| {
        let p = point_in::<3>(&gps_in, "GPSFactorArm gpsIn")?;
        let arm = point_in::<3>(&lever_arm, "GPSFactorArm leverArm")?;
        (Box::new(GnssLeverArmSe3::new(key, p.into(), arm.into())), Some(copy_of(py, &p)?))
    }
);

// GTSAM's C++ `PoseToPointFactor<Pose3, Point3>`: the landmark in the pose's frame, measured.
factor_class!(
    PoseToPointFactor3D,
    (pose_key: Key, point_key: Key, measured: Bound<'_, PyAny>),
    |py| {
        let z = point_in::<3>(&measured, "PoseToPointFactor3D measured")?;
        (Box::new(PositionSe3Point3::new(pose_key, point_key, z.into())), Some(copy_of(py, &z)?))
    }
);

// A BAL observation: the pixel at which a `SnavelyCamera` sees a point (`camera.rs`).
factor_class!(
    SnavelyReprojectionFactor,
    (camera_key: Key, point_key: Key, measured: Bound<'_, PyAny>),
    |py| {
        let uv = point_in::<2>(&measured, "SnavelyReprojectionFactor measured")?;
        (Box::new(ReprojectionSnavely::new(camera_key, point_key, uv.into())), Some(copy_of(py, &uv)?))
    }
);

/// The class a file's factor is given, and what its `measured()` returns.
pub fn classify(py: Python<'_>, factor: &dyn Factor) -> PyResult<(FactorClass, Option<Py<PyAny>>)> {
    let any = factor.as_any();
    if let Some(f) = any.downcast_ref::<BetweenSe2>() {
        return Ok((
            FactorClass::BetweenFactorPose2,
            Some(Py::new(py, Pose2::from_se2(f.measurement))?.into_any()),
        ));
    }
    if let Some(f) = any.downcast_ref::<BetweenSe3>() {
        return Ok((
            FactorClass::BetweenFactorPose3,
            Some(Py::new(py, Pose3::from_se3(f.measurement))?.into_any()),
        ));
    }
    if let Some(f) = any.downcast_ref::<PriorSe2>() {
        return Ok((
            FactorClass::PriorFactorPose2,
            Some(Py::new(py, Pose2::from_se2(f.measurement))?.into_any()),
        ));
    }
    if let Some(f) = any.downcast_ref::<PriorSe3>() {
        return Ok((
            FactorClass::PriorFactorPose3,
            Some(Py::new(py, Pose3::from_se3(f.measurement))?.into_any()),
        ));
    }
    if let Some(f) = any.downcast_ref::<ReprojectionSnavely>() {
        return Ok((
            FactorClass::SnavelyReprojectionFactor,
            Some(copy_of(py, f.observed.as_slice())?),
        ));
    }
    if let Some(f) = any.downcast_ref::<BearingRangeSe2>() {
        let m = (Py::new(py, Rot2 { theta: f.bearing })?, f.range);
        return Ok((
            FactorClass::BearingRangeFactor2D,
            Some(m.into_pyobject(py)?.into_any().unbind()),
        ));
    }
    Ok((FactorClass::Other, None))
}

/// A factor of a file, as a graph keeps it: its noise model in GTSAM's order.
pub fn from_library(
    py: Python<'_>,
    factor: Arc<dyn Factor>,
    sqrt_information: SqrtInformation,
    robust: Option<RobustKernel>,
    label: String,
) -> PyResult<FactorData> {
    let (class, measured) = classify(py, factor.as_ref())?;
    let library_information = sqrt_information.information();
    let information = if swaps_pose3_halves(class) {
        swap_pose3_information(&library_information)
    } else {
        library_information
    };
    Ok(FactorData {
        factor,
        sqrt_information,
        robust,
        noise: NoiseModel {
            information,
            robust,
            family: "Gaussian",
        },
        label,
        class,
        measured,
    })
}
