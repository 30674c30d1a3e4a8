//! The checks a definition passes before any session uses it: no part that is non-finite
//! whatever the values, a residual that is finite somewhere, and forward-mode Jacobians that
//! agree with central differences through the variables' retractions (the shared helper every
//! built-in factor is checked with) at random values.

use std::sync::Arc;

use nalgebra::Vector2;

use super::factor::{push_se3, ExpressionType, ParamKind};
use super::DefinitionError;
use crate::factors::testing::{numeric_jacobian, Rng};
use crate::factors::Factor;
use crate::geometry::{Point2, Point3, SnavelyCamera};
use crate::variables::Variable;

/// Random points at which a definition is evaluated.
const SAMPLES: usize = 16;
/// Analytic and numeric derivatives agree within this, relative to the entry's size.
const TOLERANCE: f64 = 1e-4;

fn random_variable(kind: &str, rng: &mut Rng) -> Box<dyn Variable> {
    match kind {
        "se2" => Box::new(rng.se2()),
        "se3" => Box::new(rng.se3()),
        "point2" => Box::new(Point2(Vector2::new(4.0 * rng.normal(), 4.0 * rng.normal()))),
        "point3" => Box::new(Point3(rng.vector3(4.0))),
        "snavely_camera" => {
            let pose = rng.se3();
            Box::new(SnavelyCamera {
                rotation: pose.rotation,
                translation: pose.translation,
                focal: 500.0 * (1.0 + 0.2 * rng.uniform()),
                k1: 0.01 * rng.normal(),
                k2: 0.001 * rng.normal(),
            })
        }
        _ => unreachable!("kinds are checked at compile time"),
    }
}

fn random_parameters(kinds: &[ParamKind], rng: &mut Rng) -> Vec<f64> {
    let mut params = Vec::new();
    for kind in kinds {
        match kind {
            ParamKind::Se2 => {
                let p = rng.se2();
                params.extend_from_slice(&[p.x, p.y, p.theta]);
            }
            ParamKind::Se3 => {
                let p = rng.se3();
                push_se3(&mut params, &p.rotation, &p.translation);
            }
            other => params.extend((0..other.wire_len()).map(|_| rng.normal())),
        }
    }
    params
}

/// The first entry where `a` and `b` differ by more than [`TOLERANCE`] relative to their size.
fn first_disagreement(a: &[f64], b: &[f64]) -> Option<usize> {
    a.iter()
        .zip(b)
        .position(|(x, y)| (x - y).abs() > TOLERANCE * (1.0 + x.abs().max(y.abs())))
}

pub(super) fn check(ty: &Arc<ExpressionType>) -> Result<(), DefinitionError> {
    if let Some(slot) = ty.first_constant_non_finite() {
        return Err(DefinitionError {
            path: ty.path_of(slot).to_string(),
            message: "this part is not a finite number, whatever the values".into(),
        });
    }
    let mut rng = Rng::new(0x5eed_f4c7);
    let dim = ty.residual_dim();
    let mut first_non_finite = None;
    let (mut finite, mut checked, mut mismatches) = (0, 0, 0);
    let mut first_mismatch = None;
    for _ in 0..SAMPLES {
        let variables: Vec<Box<dyn Variable>> = ty
            .variable_kinds()
            .iter()
            .map(|k| random_variable(k, &mut rng))
            .collect();
        let keys: Vec<u64> = (0..variables.len() as u64).collect();
        let probe = ty.with_parameters(&keys, random_parameters(ty.parameter_kinds(), &mut rng));
        let refs: Vec<&dyn Variable> = variables.iter().map(|v| v.as_ref()).collect();
        let cols: usize = variables.iter().map(|v| v.tangent_dim()).sum();
        let mut error = vec![0.0; dim];
        let mut analytic = vec![0.0; dim * cols];
        let bad = ty
            .evaluate_at(&refs, probe.fixed(), &mut error, Some(&mut analytic))
            .expect("variables are made of the declared kinds");
        if let Some(slot) = bad {
            first_non_finite.get_or_insert(slot);
            continue;
        }
        if !analytic.iter().all(|v| v.is_finite()) {
            continue;
        }
        finite += 1;
        let numeric = numeric_jacobian(&probe as &dyn Factor, &variables, 1e-6);
        // Near a pole (a point on a camera's plane) central differences themselves change with
        // the step: such a sample cannot judge the derivative, so it is not counted.
        let coarse = numeric_jacobian(&probe as &dyn Factor, &variables, 1e-4);
        if first_disagreement(&numeric, &coarse).is_some() {
            continue;
        }
        checked += 1;
        if let Some(k) = first_disagreement(&analytic, &numeric) {
            let (a, n) = (analytic[k], numeric[k]);
            mismatches += 1;
            first_mismatch.get_or_insert((k / cols, k % cols, a, n));
        }
    }
    if finite == 0 {
        let path = first_non_finite.map_or("residual", |s| ty.path_of(s));
        return Err(DefinitionError {
            path: path.to_string(),
            message: format!(
                "the residual is not finite at any of {SAMPLES} random values (this part is the first that is not)"
            ),
        });
    }
    if checked == 0 {
        return Err(DefinitionError {
            path: "residual".into(),
            message: format!(
                "its derivative cannot be checked: central differences change with the step at \
                 every one of {finite} finite samples (is the residual continuous?)"
            ),
        });
    }
    // A kink (abs at 0, wrap at ±π) can meet a sample by chance; most samples disagreeing means
    // the expression is not differentiable where it is used.
    if mismatches * 4 > checked {
        let (row, col, a, n) = first_mismatch.expect("counted");
        return Err(DefinitionError {
            path: "residual".into(),
            message: format!(
                "its derivative is not continuous where it was sampled: d residual[{row}] / d tangent[{col}] \
                 is {a} by differentiation and {n} by central differences ({mismatches} of {checked} samples disagree)"
            ),
        });
    }
    Ok(())
}
