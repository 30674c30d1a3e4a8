//! How far a factor that is not in the engine yet is from what the estimate predicts, measured
//! in its own noise *and* the estimate's uncertainty: the gate a possibly wrong loop closure
//! passes before it enters a streaming session's problem.
//!
//! Linearised at the estimate, with the factor's whitened residual `e`, whitened Jacobian `J`
//! (over its free variables) and their joint marginal covariance `P`, the innovation's
//! Mahalanobis distance is
//!
//! ```text
//! d² = eᵀ (I + J P Jᵀ)⁻¹ e = eᵀe − gᵀ (P⁻¹ + G)⁻¹ g,   g = Jᵀe, G = JᵀJ   (Woodbury)
//! ```
//!
//! which is also what the least-squares cost would rise by if the factor were added and the
//! linearised problem solved again: exactly χ²(dim e) distributed for a correct measurement of a
//! linear problem. Why not the factor's own whitened error `eᵀe` at the estimate: a correct loop
//! closure after a long excursion has a large error there (the drift it is about to correct);
//! `P` grows with that drift and the distance does not.
//!
//! `P` comes from the engine's factor `H = L Lᵀ`: `P = Eᵀ H⁻¹ E = (L⁻¹E)ᵀ(L⁻¹E)` for the
//! selector `E` of the factor's variables, and `L⁻¹E` is nonzero only on the elimination-tree
//! paths from those variables to the root, so the forward substitution visits those columns
//! only (the same paths an update that added the factor would refactor).

use std::collections::HashMap;

use nalgebra::{DMatrix, DVector};

use super::{dense, IncrementalEngine};
use crate::factors::EvaluationError;
use crate::problem::{FactorEntry, Problem};
use crate::solver::linearize::{factor_normal_equations, Scratch};
use crate::variables::Variable;

impl IncrementalEngine {
    /// `d²` of `entry` (a factor of `problem` the engine has not taken in) at the problem's
    /// current values. `None` when the engine does not know one of its variables yet, or when
    /// the linearised system says nothing (no free variable, a singular block).
    pub fn innovation(
        &self,
        problem: &Problem,
        entry: &FactorEntry,
    ) -> Result<Option<f64>, EvaluationError> {
        let vars = entry.variables();
        if vars.iter().any(|&v| v >= self.theta.len()) {
            return Ok(None);
        }
        let refs: Vec<&dyn Variable> = vars.iter().map(|&v| problem.values.variable(v)).collect();
        let mut scratch = Scratch::default();
        let (chi2, gram, gradient) = factor_normal_equations(entry, &refs, &mut scratch)?;
        let cols = gradient.len();
        // The factor's columns that belong to free variables, and those variables' columns in P.
        let mut selected = Vec::new();
        let mut free_vars = Vec::new();
        let mut col = 0;
        for (&v, r) in vars.iter().zip(&refs) {
            let d = r.tangent_dim();
            if self.free[v] && self.dims[v] == d && d > 0 {
                free_vars.push(v);
                selected.extend(col..col + d);
            }
            col += d;
        }
        if selected.is_empty() {
            return Ok(Some(chi2));
        }
        let Some(p) = self.joint_covariance(&free_vars) else {
            return Ok(None);
        };
        let k = selected.len();
        let g = DVector::from_iterator(k, selected.iter().map(|&i| gradient[i]));
        let mut m = DMatrix::from_fn(k, k, |i, j| gram[selected[i] * cols + selected[j]]);
        let Some(p_inverse) = p.cholesky().map(|c| c.inverse()) else {
            return Ok(None);
        };
        m += p_inverse;
        let Some(solved) = m.cholesky().map(|c| c.solve(&g)) else {
            return Ok(None);
        };
        Ok(Some((chi2 - g.dot(&solved)).max(0.0)))
    }

    /// The joint marginal covariance of the free variables `vars` (in that order, their tangent
    /// dimensions), from the engine's factor at its linearisation point.
    fn joint_covariance(&self, vars: &[usize]) -> Option<DMatrix<f64>> {
        let factor = &self.factor;
        // The union of the variables' paths to the root, in elimination order.
        let mut reach: Vec<usize> = Vec::new();
        let mut seen: HashMap<usize, usize> = HashMap::new();
        for &v in vars {
            let mut at = Some(v);
            while let Some(u) = at {
                if seen.insert(u, 0).is_some() {
                    break;
                }
                reach.push(u);
                at = factor.parent(u);
            }
        }
        reach.sort_unstable_by_key(|&u| factor.rank[u]);
        for (i, &u) in reach.iter().enumerate() {
            seen.insert(u, i);
        }
        // The right-hand side E: an identity block per variable, at its columns.
        let k: usize = vars.iter().map(|&v| factor.dim[v]).sum();
        let mut first_column = HashMap::new();
        let mut c = 0;
        for &v in vars {
            first_column.insert(v, c);
            c += factor.dim[v];
        }
        // Per reached column, `E_r − Σ L_rk w_k` (d_r × k, column-major) while it waits its
        // turn, then its `w_r = L_rr⁻¹ (…)`.
        let mut w: Vec<Vec<f64>> = reach
            .iter()
            .map(|&u| vec![0.0; factor.dim[u] * k])
            .collect();
        let mut p = DMatrix::<f64>::zeros(k, k);
        for (i, &r) in reach.iter().enumerate() {
            let d = factor.dim[r];
            let mut z = std::mem::take(&mut w[i]);
            if let Some(&c0) = first_column.get(&r) {
                for a in 0..d {
                    z[(c0 + a) * d + a] += 1.0;
                }
            }
            let column = &factor.columns[r];
            for j in 0..k {
                dense::forward(&column.diagonal, &mut z[j * d..(j + 1) * d], d);
            }
            for &(u, at) in &column.rows {
                let u = u as usize;
                // Every row of a column is one of its ancestors, so it is in the reach.
                let &target = seen.get(&u)?;
                let du = factor.dim[u];
                let l_ur = &column.blocks[at as usize..at as usize + du * d];
                let out = &mut w[target];
                for j in 0..k {
                    let zj = &z[j * d..(j + 1) * d];
                    for a in 0..du {
                        let row = &l_ur[a * d..(a + 1) * d];
                        out[j * du + a] -= row.iter().zip(zj).map(|(l, x)| l * x).sum::<f64>();
                    }
                }
            }
            for a in 0..k {
                for b in 0..=a {
                    let s: f64 = (0..d).map(|x| z[a * d + x] * z[b * d + x]).sum();
                    p[(a, b)] += s;
                    if a != b {
                        p[(b, a)] += s;
                    }
                }
            }
            w[i] = z;
        }
        Some(p)
    }
}
