//! Preconditioned conjugate gradients on a symmetric positive definite system given only by its
//! product: the implicit Schur complement's inner solver. Inexact on purpose (a Newton step need
//! not be exact far from the optimum; LM's step acceptance judges the step it gets): it stops
//! when the quadratic model Q(x) = ½ xᵀAx − bᵀx stops improving, i·(Q_i − Q_{i−1}) / Q_i < η
//! (Nash and Sofer's truncated-Newton rule, Ceres' choice: the residual's norm says little
//! about the step's quality), when what more iterations could add to the model's decrease is
//! too small to matter to the caller, or when the residual fell below a relative tolerance.

use std::time::Instant;

/// How one solve ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(in crate::solver) struct CgOutcome {
    pub iterations: usize,
    /// ‖b − A x‖ / ‖b‖ at the end (0 when b is 0).
    pub relative_residual: f64,
    /// The system showed a non-positive curvature pᵀAp (not positive definite, or rounding at
    /// a residual too small to matter): x is the last iterate, still a descent direction.
    pub breakdown: bool,
}

/// The vectors one solve needs, kept between solves (the reduced system's size each).
#[derive(Debug, Default)]
pub(in crate::solver) struct CgWork {
    residual: Vec<f64>,
    preconditioned: Vec<f64>,
    direction: Vec<f64>,
    product: Vec<f64>,
}

impl CgWork {
    pub fn new(n: usize) -> Self {
        Self {
            residual: vec![0.0; n],
            preconditioned: vec![0.0; n],
            direction: vec![0.0; n],
            product: vec![0.0; n],
        }
    }
}

/// When a solve stops: the first of these met.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(in crate::solver) struct CgStop {
    /// ‖r‖ ≤ `residual` ‖b‖.
    pub residual: f64,
    /// i·(Q_i − Q_{i−1}) / Q_i < `model` (0: never).
    pub model: f64,
    /// i·(Q_{i−1} − Q_i) < `gain` (0: never): what more iterations could add to the model's
    /// decrease no longer matters (the caller's tolerance on the step's gain, in Q's units).
    pub gain: f64,
    pub max_iterations: usize,
    /// The solve's time limit: no iteration starts past it once one has run (a solve stopped
    /// by `limits.max_solve_ms` must not spend hundreds of products first; at 5 000 cameras one
    /// product is most of a second). `None`: no limit.
    pub deadline: Option<Instant>,
}

/// Solves A x = b from x = 0, with `product(v, out)` writing A v and `precondition(r, out)`
/// writing M⁻¹ r (M symmetric positive definite, close to A), until `stop`.
pub(in crate::solver) fn solve(
    mut product: impl FnMut(&[f64], &mut [f64]),
    mut precondition: impl FnMut(&[f64], &mut [f64]),
    b: &[f64],
    x: &mut [f64],
    stop: CgStop,
    work: &mut CgWork,
) -> CgOutcome {
    let CgWork {
        residual: r,
        preconditioned: z,
        direction: p,
        product: q,
    } = work;
    x.fill(0.0);
    r.copy_from_slice(b);
    let b_norm = norm(b);
    let mut outcome = CgOutcome {
        iterations: 0,
        relative_residual: 0.0,
        breakdown: false,
    };
    if b_norm == 0.0 {
        return outcome;
    }
    precondition(r, z);
    p.copy_from_slice(z);
    let mut rz = dot(r, z);
    outcome.relative_residual = 1.0;
    // Q(x) = −½ (bᵀx + rᵀx), since Ax = b − r; 0 at x = 0.
    let mut model = 0.0;
    while outcome.iterations < stop.max_iterations && outcome.relative_residual > stop.residual {
        if outcome.iterations > 0 && stop.deadline.is_some_and(|d| Instant::now() >= d) {
            break;
        }
        product(p, q);
        let curvature = dot(p, q);
        if !(curvature > 0.0 && curvature.is_finite() && rz > 0.0) {
            outcome.breakdown = true;
            break;
        }
        let alpha = rz / curvature;
        for ((xi, ri), (pi, qi)) in x.iter_mut().zip(r.iter_mut()).zip(p.iter().zip(q.iter())) {
            *xi += alpha * pi;
            *ri -= alpha * qi;
        }
        outcome.iterations += 1;
        outcome.relative_residual = norm(r) / b_norm;
        let next_model = -0.5 * (dot(b, x) + dot(r, x));
        let gained = outcome.iterations as f64 * (model - next_model);
        let improvement = -gained / next_model;
        model = next_model;
        if (stop.model > 0.0 && improvement < stop.model) || (stop.gain > 0.0 && gained < stop.gain)
        {
            break;
        }
        precondition(r, z);
        let rz_next = dot(r, z);
        let beta = rz_next / rz;
        rz = rz_next;
        for (pi, zi) in p.iter_mut().zip(z.iter()) {
            *pi = zi + beta * *pi;
        }
    }
    outcome
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn residual(residual: f64, max_iterations: usize) -> CgStop {
        CgStop {
            residual,
            model: 0.0,
            gain: 0.0,
            max_iterations,
            deadline: None,
        }
    }

    /// A random-ish SPD matrix (diagonally dominant), row-major.
    fn spd(n: usize) -> Vec<f64> {
        let mut a = vec![0.0; n * n];
        let mut seed = 12345_u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for i in 0..n {
            for j in 0..i {
                let v = next();
                a[i * n + j] = v;
                a[j * n + i] = v;
            }
        }
        for i in 0..n {
            let row: f64 = (0..n).map(|j| a[i * n + j].abs()).sum();
            a[i * n + i] = row + 0.1 + (i as f64) * 0.05;
        }
        a
    }

    fn multiply(a: &[f64], n: usize, v: &[f64], out: &mut [f64]) {
        for i in 0..n {
            out[i] = (0..n).map(|j| a[i * n + j] * v[j]).sum();
        }
    }

    /// The exact solution by Gaussian elimination (no pivoting: A is SPD).
    fn direct(a: &[f64], n: usize, b: &[f64]) -> Vec<f64> {
        let (mut m, mut x) = (a.to_vec(), b.to_vec());
        for k in 0..n {
            for i in k + 1..n {
                let f = m[i * n + k] / m[k * n + k];
                for j in k..n {
                    m[i * n + j] -= f * m[k * n + j];
                }
                x[i] -= f * x[k];
            }
        }
        for k in (0..n).rev() {
            let s: f64 = (k + 1..n).map(|j| m[k * n + j] * x[j]).sum();
            x[k] = (x[k] - s) / m[k * n + k];
        }
        x
    }

    #[test]
    fn preconditioned_cg_matches_the_direct_solve() {
        let n = 40;
        let a = spd(n);
        let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
        let exact = direct(&a, n, &b);
        let mut x = vec![0.0; n];
        let mut work = CgWork::new(n);
        let jacobi = |r: &[f64], z: &mut [f64]| {
            for i in 0..n {
                z[i] = r[i] / a[i * n + i];
            }
        };
        let outcome = solve(
            |v, out| multiply(&a, n, v, out),
            jacobi,
            &b,
            &mut x,
            residual(1e-13, 200),
            &mut work,
        );
        assert!(!outcome.breakdown);
        assert!(outcome.relative_residual <= 1e-13, "{outcome:?}");
        let error = x
            .iter()
            .zip(&exact)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f64::max);
        assert!(error < 1e-10, "max error {error}");
        // A looser tolerance stops earlier with the residual it promised.
        let loose = solve(
            |v, out| multiply(&a, n, v, out),
            jacobi,
            &b,
            &mut x,
            residual(1e-2, 200),
            &mut work,
        );
        assert!(
            loose.iterations < outcome.iterations,
            "{loose:?} vs {outcome:?}"
        );
        assert!(loose.relative_residual <= 1e-2);
        let mut ax = vec![0.0; n];
        multiply(&a, n, &x, &mut ax);
        let r: f64 = ax
            .iter()
            .zip(&b)
            .map(|(p, q)| (p - q).powi(2))
            .sum::<f64>()
            .sqrt();
        let b_norm = b.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((r / b_norm - loose.relative_residual).abs() < 1e-9);
        // The model rule stops earlier still, at a step whose model value is within the rule's
        // tolerance of the optimum's −½ bᵀx*.
        let model_stop = CgStop {
            residual: 1e-13,
            model: 1e-2,
            gain: 0.0,
            max_iterations: 200,
            deadline: None,
        };
        let truncated = solve(
            |v, out| multiply(&a, n, v, out),
            jacobi,
            &b,
            &mut x,
            model_stop,
            &mut work,
        );
        assert!(truncated.iterations < outcome.iterations, "{truncated:?}");
        let q = |x: &[f64]| {
            let mut ax = vec![0.0; n];
            multiply(&a, n, x, &mut ax);
            0.5 * x.iter().zip(&ax).map(|(p, q)| p * q).sum::<f64>()
                - x.iter().zip(&b).map(|(p, q)| p * q).sum::<f64>()
        };
        let (reached, best) = (q(&x), q(&exact));
        assert!(
            reached < 0.0 && (reached - best) / best.abs() < 1e-2,
            "{reached} vs {best}"
        );
        // The gain rule: stopped once i·(Q_{i−1} − Q_i) fell below 1e-3 |Q*|, before the
        // residual rule, within a few times that of the optimum.
        let gain_stop = CgStop {
            model: 0.0,
            gain: 1e-3 * best.abs(),
            ..model_stop
        };
        let gained = solve(
            |v, out| multiply(&a, n, v, out),
            jacobi,
            &b,
            &mut x,
            gain_stop,
            &mut work,
        );
        assert!(gained.iterations < outcome.iterations, "{gained:?}");
        let reached = q(&x);
        assert!((reached - best) / best.abs() < 1e-2, "{reached} vs {best}");
    }

    #[test]
    fn a_zero_right_hand_side_and_an_indefinite_matrix_end_at_once() {
        let mut x = vec![1.0; 3];
        let mut work = CgWork::new(3);
        let identity = |v: &[f64], out: &mut [f64]| out.copy_from_slice(v);
        let zero = solve(
            identity,
            identity,
            &[0.0; 3],
            &mut x,
            residual(1e-6, 10),
            &mut work,
        );
        assert_eq!((zero.iterations, x.clone()), (0, vec![0.0; 3]));
        let negative = |v: &[f64], out: &mut [f64]| {
            for (o, x) in out.iter_mut().zip(v) {
                *o = -x;
            }
        };
        let bad = solve(
            negative,
            identity,
            &[1.0, 2.0, 3.0],
            &mut x,
            residual(1e-6, 10),
            &mut work,
        );
        assert!(bad.breakdown && bad.iterations == 0);
    }

    /// Past the solve's deadline CG stops after the iteration it is in (at least one, so the
    /// step is not nil), with the iterate it reached.
    #[test]
    fn a_passed_deadline_stops_after_one_iteration() {
        let n = 40;
        let a = spd(n);
        let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).cos()).collect();
        let mut x = vec![0.0; n];
        let mut work = CgWork::new(n);
        let identity = |r: &[f64], z: &mut [f64]| z.copy_from_slice(r);
        let passed = CgStop {
            deadline: Some(Instant::now()),
            ..residual(1e-13, 200)
        };
        let stopped = solve(
            |v, out| multiply(&a, n, v, out),
            identity,
            &b,
            &mut x,
            passed,
            &mut work,
        );
        assert_eq!(stopped.iterations, 1, "{stopped:?}");
        assert!(x.iter().any(|v| *v != 0.0) && stopped.relative_residual < 1.0);
        let free = solve(
            |v, out| multiply(&a, n, v, out),
            identity,
            &b,
            &mut x,
            residual(1e-13, 200),
            &mut work,
        );
        assert!(free.iterations > 1, "{free:?}");
    }
}
