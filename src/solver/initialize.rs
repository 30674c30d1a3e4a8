//! Initialisation for pose graphs when the given guess is poor.
//!
//! Both variants solve two *linear* least-squares problems on the same sparse machinery as the
//! optimiser, anchored on the variables held fixed for the solve:
//!
//! * 2D: orientations first. A breadth-first spanning tree from the anchors fixes each edge's
//!   2π ambiguity, `k_ij = round((θ̃_j − θ̃_i − θ_ij)/2π)`; then `min Σ w_ij (θ_j − θ_i − θ_ij − 2πk_ij)²`
//!   with `w_ij` the marginal rotation information. Positions follow from
//!   `min Σ w_t ‖t_j − t_i − R(θ_i) t_ij‖²` with the orientations held (Carlone et al.'s LAGO
//!   idea), `w_t` the mean eigenvalue of the marginal translation information: isotropic weights
//!   make both steps scalar Laplacians sharing one symbolic factorisation, and anisotropic ones
//!   (condition numbers up to 2.4e11 on input_INTEL) gave a far worse start.
//! * 3D: chordal relaxation (Martinec & Pajdla; Carlone et al. 2015): `min Σ w_ij ‖R_j − R_i R_ij‖²_F`
//!   over unconstrained 3×3 matrices — three independent systems (one per row of R) sharing one
//!   matrix — then each R is projected onto SO(3) by SVD, and translations come from
//!   `min Σ w ‖t_j − t_i − R_i t_ij‖²`. In 3D both weights are the mean diagonal information of
//!   the block (rotation, translation).
//!
//! Priors act as edges to a fixed world frame. Graphs with any other factor kind are left alone.

mod planar;

use std::borrow::Borrow;
use std::cell::Cell;

use faer::sparse::linalg::SupernodalThreshold;
use nalgebra::{Matrix3, RowVector3, SMatrix, UnitQuaternion};

use super::budget::{Budget, FactorCost};
use super::cholesky::SparseCholesky;
use super::linearize::free_blocks;
use super::options::Initialization;
use super::structure::{BlockOrdering, BlockPattern};
use super::supernodes::BlockSupernodes;
use crate::factors::{BetweenSe3, PriorSe3, SqrtInformation};
use crate::geometry::Se3;
use crate::problem::FactorEntry;

use crate::problem::{Problem, Values};

/// How much lower the chordal chi2 must be for `Initialization::Auto` to start from it.
const AUTO_INIT_GAIN: f64 = 10.0;

/// The chordal estimate a solve may start from, when `mode` asks for one; otherwise (or when
/// it does not apply or the budget stopped it) `Err` with how the solve was initialised. Whether
/// the estimate is taken depends on its chi2 ([`take_estimate`]), which the solve learns from
/// its first linearisation there instead of a separate evaluation.
pub(super) fn chordal_estimate(
    problem: &Problem,
    fixed: &[bool],
    ordering: &BlockOrdering,
    shared: Option<&BlockSupernodes>,
    mode: Initialization,
    budget: &dyn Budget,
) -> Result<Values, String> {
    if mode == Initialization::None {
        return Err("none".into());
    }
    let stopped = Cell::new(false);
    chordal(
        problem.factors(),
        &problem.values,
        fixed,
        ordering,
        shared,
        &Stoppable {
            budget,
            stopped: &stopped,
        },
    )
    .ok_or_else(|| {
        let why = if stopped.get() {
            "stopped by the solve's budget"
        } else {
            "not a pose graph"
        };
        format!("none ({why})")
    })
}

/// Whether a solve initialised as `mode` starts from the chordal estimate of chi2 `chi2`
/// (`Ok` with the label) or from the given values of chi2 `initial_chi2` (`Err` with the label).
pub(super) fn take_estimate(
    mode: Initialization,
    chi2: f64,
    initial_chi2: f64,
) -> Result<String, String> {
    let take = match mode {
        Initialization::Chordal => chi2.is_finite(),
        _ => chi2.is_finite() && chi2 * AUTO_INIT_GAIN < initial_chi2,
    };
    if take {
        Ok("chordal".into())
    } else {
        Err(format!(
            "given values (chordal chi2 {chi2:.6e} was not {AUTO_INIT_GAIN}x lower)"
        ))
    }
}

/// The budget as the initialisation sees it: it remembers having stopped the work, to tell that
/// apart from a graph the chordal estimate does not apply to (both give `None`).
pub struct Stoppable<'a> {
    pub budget: &'a dyn Budget,
    pub stopped: &'a Cell<bool>,
}

impl Stoppable<'_> {
    /// Whether a factorisation of `flops` may start now.
    fn may_factorize(&self, flops: f64) -> bool {
        let cost = FactorCost {
            flops,
            measured_rate: None,
        };
        let go = self.budget.checkpoint().is_continue() && cost.fits(self.budget);
        if !go {
            self.stopped.set(true);
        }
        go
    }
}

/// The chordal estimate, or `None` when the problem is not a pure SE(2) or SE(3) pose graph, or a
/// linear system turned out singular (then the given values are used).
///
/// `ordering` is the free variables' graph ([`super::linearize::free_adjacency`]) with its
/// elimination order; `shared`, the solve's supernodes over it in blocks when it has them, also
/// serve the 2D steps' scalar Laplacians (no second analysis).
pub fn chordal<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    ordering: &BlockOrdering,
    shared: Option<&BlockSupernodes>,
    budget: &Stoppable,
) -> Option<Values> {
    chordal_unwrapping(factors, values, fixed, ordering, shared, budget, false)
}

/// [`chordal`] with the 2D orientations' 2π ambiguities resolved at `values` (each edge's
/// wrap taken where the current estimate puts it) instead of along a spanning tree of the
/// measurements: for a re-estimate during graduated non-convexity, where a tree could run
/// through a wrong closure. 3D has no such ambiguity (rotation matrices), so it is [`chordal`].
pub fn chordal_unwrapped_at_values<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    ordering: &BlockOrdering,
    budget: &Stoppable,
) -> Option<Values> {
    chordal_unwrapping(factors, values, fixed, ordering, None, budget, true)
}

fn chordal_unwrapping<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    ordering: &BlockOrdering,
    shared: Option<&BlockSupernodes>,
    budget: &Stoppable,
    unwrap_at_values: bool,
) -> Option<Values> {
    if values.is_empty() {
        return None;
    }
    let all = |kind: &str| (0..values.len()).all(|v| values.variable(v).kind() == kind);
    if all("se2") {
        planar::chordal_2d(
            factors,
            values,
            fixed,
            ordering,
            shared,
            budget,
            unwrap_at_values,
        )
    } else if all("se3") {
        chordal_3d(factors, values, fixed, ordering, budget)
    } else {
        None
    }
}

/// A relative (or, with `from = None`, absolute) measurement between variable indices.
struct Edge<'a, M> {
    from: Option<usize>,
    to: usize,
    measurement: M,
    sqrt_information: &'a SqrtInformation,
}

fn collect_edges<E: Borrow<FactorEntry>, M: Copy>(
    factors: &[E],
    between: impl Fn(&FactorEntry) -> Option<M>,
    prior: impl Fn(&FactorEntry) -> Option<M>,
) -> Option<Vec<Edge<'_, M>>> {
    let mut edges = Vec::with_capacity(factors.len());
    for f in factors {
        let f = f.borrow();
        let vars = f.variables();
        let sqrt_information = &f.sqrt_information;
        if let Some(m) = between(f) {
            edges.push(Edge {
                from: Some(vars[0]),
                to: vars[1],
                measurement: m,
                sqrt_information,
            });
        } else if let Some(m) = prior(f) {
            edges.push(Edge {
                from: None,
                to: vars[0],
                measurement: m,
                sqrt_information,
            });
        } else {
            return None;
        }
    }
    Some(edges)
}

/// Marginal information of the sub-block `start..start+L` of an N×N information `RᵀR` (the
/// inverse of the matching covariance block), in fixed-size arithmetic.
fn marginal_information<const N: usize, const L: usize>(
    sqrt: &SqrtInformation,
    start: usize,
) -> Option<SMatrix<f64, L, L>> {
    if sqrt.is_diagonal() {
        // Independent components: the marginal is the block itself.
        let r = sqrt.upper();
        return Some(SMatrix::from_fn(|i, j| {
            if i == j {
                r[(start + i) * (N + 1)].powi(2)
            } else {
                0.0
            }
        }));
    }
    let r = SMatrix::<f64, N, N>::from_row_slice(sqrt.upper());
    let cov = (r.transpose() * r).try_inverse()?;
    cov.fixed_view::<L, L>(start, start)
        .into_owned()
        .try_inverse()
}

/// Mean of the diagonal of `RᵀR` over `start..start+3`: an isotropic weight for that block.
fn mean_information(sqrt: &SqrtInformation, start: usize) -> f64 {
    let (r, n) = (sqrt.upper(), sqrt.dim());
    let diagonal = |k: usize| (0..=k).map(|i| r[i * n + k] * r[i * n + k]).sum::<f64>();
    (start..start + 3).map(diagonal).sum::<f64>() / 3.0
}

/// A pattern and its symbolic Cholesky, shared by the systems of one initialisation.
struct SymbolicCache {
    dim: usize,
    pattern: BlockPattern,
    chol: SparseCholesky,
}

/// One term `‖Σ_k J_k x_k + r0‖²_W` of a linear least-squares problem, with one or two
/// variables, D-dimensional residuals and variables, and R right-hand sides.
struct Term<const D: usize, const R: usize> {
    vars: [(usize, SMatrix<f64, D, D>); 2],
    count: usize,
    r0: SMatrix<f64, D, R>,
    weight: SMatrix<f64, D, D>,
}

/// Dense-block linear least squares over the free variables, several right-hand sides at once.
/// Fixed variables' contributions are folded into r0 as terms are added.
struct LinearLeastSquares<'a, const D: usize, const R: usize> {
    fixed_value: &'a [Option<SMatrix<f64, D, R>>],
    block: Vec<Option<usize>>,
    terms: Vec<Term<D, R>>,
}

impl<'a, const D: usize, const R: usize> LinearLeastSquares<'a, D, R> {
    fn new(fixed_value: &'a [Option<SMatrix<f64, D, R>>], capacity: usize) -> Self {
        // The ordering's graph numbers free variables this way; the systems must agree with it.
        let (block, _) = free_blocks(fixed_value.iter().map(Option::is_some));
        Self {
            fixed_value,
            block,
            terms: Vec::with_capacity(capacity),
        }
    }

    fn add(
        &mut self,
        vars: &[(usize, SMatrix<f64, D, D>)],
        r0: SMatrix<f64, D, R>,
        weight: SMatrix<f64, D, D>,
    ) {
        let mut term = Term {
            vars: [(0, SMatrix::zeros()); 2],
            count: 0,
            r0,
            weight,
        };
        for &(v, j) in vars {
            match &self.fixed_value[v] {
                Some(x) => term.r0 += j * x,
                None => {
                    term.vars[term.count] = (v, j);
                    term.count += 1;
                }
            }
        }
        if term.count > 0 {
            self.terms.push(term);
        }
    }

    /// Solution per variable; fixed variables get their fixed value.
    fn solve(
        self,
        ordering: &BlockOrdering,
        cache: &mut Option<SymbolicCache>,
        budget: &Stoppable,
    ) -> Option<Vec<SMatrix<f64, D, R>>> {
        let nb = self.block.iter().flatten().count();
        if cache.as_ref().is_none_or(|c| c.dim != D) {
            let pattern = BlockPattern::with_ordering(&vec![D; nb], ordering);
            // faer's heuristic here: the scalar Laplacians of the 2D steps factor faster
            // simplicial (no per-supernode gemm dispatch; M3500: −5% instructions per solve),
            // the 3×3-block rotation system of 3D supernodal.
            let chol = SparseCholesky::analyze(&pattern, SupernodalThreshold::AUTO).ok()?;
            *cache = Some(SymbolicCache {
                dim: D,
                pattern,
                chol,
            });
        }
        let SymbolicCache { pattern, chol, .. } = cache.as_mut()?;
        let pattern = &*pattern;
        let mut h = vec![0.0; pattern.nnz()];
        let mut rhs = vec![vec![0.0; pattern.n]; R];
        for t in &self.terms {
            let vars = &t.vars[..t.count];
            for &(va, ja) in vars {
                let pa = pattern.position[self.block[va]?];
                let jtw = ja.transpose() * t.weight;
                let g = -(jtw * t.r0);
                for c in 0..R {
                    for q in 0..D {
                        rhs[c][pattern.offset[pa] + q] += g[(q, c)];
                    }
                }
                for &(vb, jb) in vars {
                    let pb = pattern.position[self.block[vb]?];
                    if pa < pb {
                        continue;
                    }
                    let hab = jtw * jb;
                    let pair = pattern.pair(pa, pb)?;
                    for q in 0..D {
                        let rows = if pa == pb { q } else { 0 };
                        for r in rows..D {
                            h[pattern.value_index(pair, pa == pb, r, q)] += hab[(r, q)];
                        }
                    }
                }
            }
        }
        if !budget.may_factorize(chol.factor_flops()) {
            return None;
        }
        chol.factorize(pattern, &h).ok()?;
        for r in rhs.iter_mut() {
            chol.solve_in_place(r);
        }
        let mut out = Vec::with_capacity(self.fixed_value.len());
        for (v, fixed) in self.fixed_value.iter().enumerate() {
            out.push(match fixed {
                Some(x) => *x,
                None => {
                    let o = pattern.offset[pattern.position[self.block[v]?]];
                    SMatrix::<f64, D, R>::from_fn(|q, c| rhs[c][o + q])
                }
            });
        }
        Some(out)
    }
}

fn chordal_3d<E: Borrow<FactorEntry>>(
    factors: &[E],
    values: &Values,
    fixed: &[bool],
    ordering: &BlockOrdering,
    budget: &Stoppable,
) -> Option<Values> {
    let edges = collect_edges(
        factors,
        |f| {
            f.factor
                .as_any()
                .downcast_ref::<BetweenSe3>()
                .map(|b| b.measurement)
        },
        |f| {
            f.factor
                .as_any()
                .downcast_ref::<PriorSe3>()
                .map(|p| p.measurement)
        },
    )?;
    let n = values.len();
    let pose = |v: usize| {
        *values
            .variable(v)
            .as_any()
            .downcast_ref::<Se3>()
            .expect("checked kind")
    };
    let identity = Matrix3::identity();
    // Unknown per pose: Rᵀ (its columns are the rows of R), one right-hand side per row.
    let fixed_r: Vec<Option<Matrix3<f64>>> = (0..n)
        .map(|v| fixed[v].then(|| pose(v).rotation_matrix().transpose()))
        .collect();
    let mut rot = LinearLeastSquares::new(&fixed_r, edges.len());
    for e in &edges {
        let rz = e.measurement.rotation_matrix();
        let w = Matrix3::identity() * mean_information(e.sqrt_information, 3);
        match e.from {
            // R_j − R_i R_ij = 0, row k: x_j − R_ijᵀ x_i = 0 with x = (row k of R)ᵀ.
            Some(i) => rot.add(
                &[(e.to, identity), (i, -rz.transpose())],
                Matrix3::zeros(),
                w,
            ),
            None => rot.add(&[(e.to, identity)], -rz.transpose(), w),
        }
    }
    let mut cache = None;
    let rotations: Vec<Matrix3<f64>> = rot
        .solve(ordering, &mut cache, budget)?
        .iter()
        .map(|rt| project_to_so3(&rt.transpose()))
        .collect();

    // Translations: a scalar Laplacian with x, y, z as three right-hand sides.
    let fixed_t: Vec<Option<RowVector3<f64>>> = (0..n)
        .map(|v| fixed[v].then(|| pose(v).translation.transpose()))
        .collect();
    let mut trans = LinearLeastSquares::new(&fixed_t, edges.len());
    let one = SMatrix::<f64, 1, 1>::identity();
    for e in &edges {
        let w = SMatrix::from_element(mean_information(e.sqrt_information, 0));
        match e.from {
            Some(i) => trans.add(
                &[(e.to, one), (i, -one)],
                -(rotations[i] * e.measurement.translation).transpose(),
                w,
            ),
            None => trans.add(&[(e.to, one)], -e.measurement.translation.transpose(), w),
        }
    }
    let t = trans.solve(ordering, &mut cache, budget)?;
    let mut out = values.clone();
    for v in 0..n {
        if !fixed[v] {
            out.set(
                v,
                &Se3::new(UnitQuaternion::from_matrix(&rotations[v]), t[v].transpose()),
            );
        }
    }
    Some(out)
}

/// The rotation nearest to `m` in Frobenius norm: U diag(1, 1, det(UVᵀ)) Vᵀ.
fn project_to_so3(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u.expect("requested"), svd.v_t.expect("requested"));
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    u * d * v_t
}
