//! `factord._native`: the factord library in process, with GTSAM's Python names and call shapes
//! (see `clients/python/native/README.md` for what is covered and what differs). The package
//! `factord` (python/factord/__init__.py) adds GTSAM's namespaces over these classes.
//!
//! Only the library's public API is used. Errors are Python exceptions of one family
//! (`errors.rs`); nothing here unwraps on user input.

use pyo3::prelude::*;

mod arrays;
mod camera;
mod custom;
mod dataset;
mod errors;
mod expression;
mod factors;
mod graph;
mod isam2;
mod keys;
mod marginals;
mod noise;
mod optimizers;
mod planar;
mod point_factors;
mod service;
mod spatial;
mod values;

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    m.add_class::<planar::Rot2>()?;
    m.add_class::<planar::Pose2>()?;
    m.add_class::<spatial::Rot3>()?;
    m.add_class::<spatial::Pose3>()?;
    m.add_class::<noise::NoiseModel>()?;
    m.add_class::<noise::MEstimator>()?;
    m.add_class::<values::Values>()?;
    m.add_class::<factors::NonlinearFactor>()?;
    m.add_class::<factors::PriorFactorPose2>()?;
    m.add_class::<factors::BetweenFactorPose2>()?;
    m.add_class::<factors::PriorFactorPose3>()?;
    m.add_class::<factors::BetweenFactorPose3>()?;
    m.add_class::<factors::BearingRangeFactor2D>()?;
    m.add_class::<factors::RangeFactor2D>()?;
    m.add_class::<factors::RangeFactorPose2>()?;
    m.add_class::<factors::RangeFactor3D>()?;
    m.add_class::<factors::RangeFactorPose3>()?;
    m.add_class::<factors::BearingFactor2D>()?;
    m.add_class::<factors::PriorFactorPoint2>()?;
    m.add_class::<factors::PriorFactorPoint3>()?;
    m.add_class::<factors::BetweenFactorPoint2>()?;
    m.add_class::<factors::BetweenFactorPoint3>()?;
    m.add_class::<factors::GPSFactor>()?;
    m.add_class::<factors::GPSFactorArm>()?;
    m.add_class::<factors::PoseToPointFactor3D>()?;
    m.add_class::<factors::SnavelyReprojectionFactor>()?;
    m.add_class::<camera::SnavelyCamera>()?;
    m.add_class::<custom::CustomFactor>()?;
    m.add_class::<expression::FactorType>()?;
    m.add_class::<graph::NonlinearFactorGraph>()?;
    m.add_class::<optimizers::OptimizerParams>()?;
    m.add_class::<optimizers::LevenbergMarquardtParams>()?;
    m.add_class::<optimizers::GaussNewtonParams>()?;
    m.add_class::<optimizers::DoglegParams>()?;
    m.add_class::<optimizers::LevenbergMarquardtOptimizer>()?;
    m.add_class::<optimizers::GaussNewtonOptimizer>()?;
    m.add_class::<optimizers::DoglegOptimizer>()?;
    m.add_class::<marginals::Marginals>()?;
    m.add_class::<marginals::JointMarginal>()?;
    m.add_class::<isam2::ISAM2Params>()?;
    m.add_class::<isam2::ISAM2Result>()?;
    m.add_class::<isam2::ISAM2>()?;
    service::register(m)?;
    m.add_function(wrap_pyfunction!(keys::symbol, m)?)?;
    m.add_function(wrap_pyfunction!(keys::symbol_chr, m)?)?;
    m.add_function(wrap_pyfunction!(keys::symbol_index, m)?)?;
    m.add_function(wrap_pyfunction!(keys::key_name_py, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::read_g2o, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::write_g2o, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::load_bal, m)?)?;
    m.add_function(wrap_pyfunction!(optimizers::solve, m)?)?;
    Ok(())
}
