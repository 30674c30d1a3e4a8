//! Initialisation for pose graphs when the given guess is poor.
//!
//! Both variants solve two *linear* least-squares problems on the same sparse machinery as the
//! optimiser, anchored on the variables held fixed for the solve:
//!
//! * 2D: orientations first. A breadth-first spanning tree from the anchors fixes each edge's
//!   2π ambiguity, `k_ij = round((θ̃_j − θ̃_i − θ_ij)/2π)`; then `min Σ w_ij (θ_j − θ_i − θ_ij − 2πk_ij)²`
//!   with `w_ij` the marginal rotation information. Positions follow from
//!   `min Σ ‖R(θ_i)ᵀ(t_j − t_i) − t_ij‖²_Ω_tt` with the orientations held (Carlone et al.'s LAGO idea).
//! * 3D: chordal relaxation (Martinec & Pajdla; Carlone et al. 2015): `min Σ w_ij ‖R_j − R_i R_ij‖²_F`
//!   over unconstrained 3×3 matrices — three independent systems (one per row of R) sharing one
//!   matrix — then each R is projected onto SO(3) by SVD, and translations come from
//!   `min Σ w ‖t_j − t_i − R_i t_ij‖²`.
//!
//! Priors act as edges to a fixed world frame. Graphs with any other factor kind are left alone.

use std::collections::VecDeque;
use std::f64::consts::PI;

use faer::sparse::linalg::SupernodalThreshold;
use nalgebra::{DMatrix, Matrix2, Matrix3, UnitQuaternion, Vector3};

use super::cholesky::SparseCholesky;
use super::structure::BlockPattern;
use crate::factors::{BetweenSe2, BetweenSe3, FactorEntry, PriorSe2, PriorSe3};
use crate::geometry::{rotation_matrix_2d, Se2, Se3};
use crate::problem::Values;

/// The chordal estimate, or `None` when the problem is not a pure SE(2) or SE(3) pose graph, or a
/// linear system turned out singular (then the given values are used).
pub fn chordal(factors: &[FactorEntry], values: &Values, fixed: &[bool]) -> Option<Values> {
    if values.is_empty() {
        return None;
    }
    let all = |kind: &str| (0..values.len()).all(|v| values.variable(v).kind() == kind);
    if all("se2") {
        chordal_2d(factors, values, fixed)
    } else if all("se3") {
        chordal_3d(factors, values, fixed)
    } else {
        None
    }
}

/// A relative (or, with `from = None`, absolute) measurement between variable indices.
struct Edge<M> {
    from: Option<usize>,
    to: usize,
    measurement: M,
    information: DMatrix<f64>,
}

fn collect_edges<M: Copy>(
    factors: &[FactorEntry],
    values: &Values,
    between: impl Fn(&FactorEntry) -> Option<M>,
    prior: impl Fn(&FactorEntry) -> Option<M>,
) -> Option<Vec<Edge<M>>> {
    let mut edges = Vec::with_capacity(factors.len());
    for f in factors {
        let keys = f.factor.keys();
        let information = f.sqrt_information.information();
        if let Some(m) = between(f) {
            edges.push(Edge {
                from: Some(values.index_of(keys[0])?),
                to: values.index_of(keys[1])?,
                measurement: m,
                information,
            });
        } else if let Some(m) = prior(f) {
            edges.push(Edge { from: None, to: values.index_of(keys[0])?, measurement: m, information });
        } else {
            return None;
        }
    }
    Some(edges)
}

/// Marginal information of the sub-block `range` of an information matrix (1 / covariance block).
fn marginal_information(information: &DMatrix<f64>, start: usize, len: usize) -> Option<DMatrix<f64>> {
    let cov = information.clone().try_inverse()?;
    cov.view((start, start), (len, len)).into_owned().try_inverse()
}

/// Dense-block linear least squares `min Σ ‖Σ_k J_k x_k + r0‖²_W` over the free variables, with
/// several right-hand sides (columns of r0 and x). Fixed variables' contributions are folded into
/// r0 as terms are added.
struct LinearLeastSquares<'a> {
    dim: usize,
    nrhs: usize,
    fixed_value: &'a [Option<DMatrix<f64>>],
    block: Vec<Option<usize>>,
    /// (variables, Jacobian blocks dim_r × dim, r0 dim_r × nrhs, W dim_r × dim_r)
    terms: Vec<(Vec<usize>, Vec<DMatrix<f64>>, DMatrix<f64>, DMatrix<f64>)>,
}

impl<'a> LinearLeastSquares<'a> {
    fn new(dim: usize, nrhs: usize, fixed_value: &'a [Option<DMatrix<f64>>]) -> Self {
        let mut block = vec![None; fixed_value.len()];
        let mut next = 0;
        for (v, f) in fixed_value.iter().enumerate() {
            if f.is_none() {
                block[v] = Some(next);
                next += 1;
            }
        }
        Self { dim, nrhs, fixed_value, block, terms: Vec::new() }
    }

    fn add(&mut self, vars: &[(usize, DMatrix<f64>)], mut r0: DMatrix<f64>, weight: DMatrix<f64>) {
        let mut free_vars = Vec::new();
        let mut jacobians = Vec::new();
        for (v, j) in vars {
            match &self.fixed_value[*v] {
                Some(x) => r0 += j * x,
                None => {
                    free_vars.push(*v);
                    jacobians.push(j.clone());
                }
            }
        }
        if !free_vars.is_empty() {
            self.terms.push((free_vars, jacobians, r0, weight));
        }
    }

    /// Solution per variable (dim × nrhs); fixed variables get their fixed value.
    fn solve(self) -> Option<Vec<DMatrix<f64>>> {
        let nb = self.block.iter().flatten().count();
        let mut adjacency = vec![Vec::new(); nb];
        for (vars, ..) in &self.terms {
            for &a in vars {
                for &b in vars {
                    if a != b {
                        adjacency[self.block[a]?].push(self.block[b]?);
                    }
                }
            }
        }
        let pattern = BlockPattern::new(&vec![self.dim; nb], &adjacency);
        let d = self.dim;
        let mut h = vec![0.0; pattern.nnz()];
        let mut rhs = vec![DMatrix::<f64>::zeros(pattern.n, 1); self.nrhs];
        for (vars, jacobians, r0, w) in &self.terms {
            let wj: Vec<DMatrix<f64>> = jacobians.iter().map(|j| w * j).collect();
            for (ka, &va) in vars.iter().enumerate() {
                let pa = pattern.position[self.block[va]?];
                let g = -(jacobians[ka].transpose() * w * r0);
                for c in 0..self.nrhs {
                    for q in 0..d {
                        rhs[c][pattern.offset[pa] + q] += g[(q, c)];
                    }
                }
                for (kb, &vb) in vars.iter().enumerate() {
                    let pb = pattern.position[self.block[vb]?];
                    if pa < pb {
                        continue;
                    }
                    let hab = jacobians[ka].transpose() * &wj[kb];
                    let pair = pattern.pair(pa, pb)?;
                    for q in 0..d {
                        let rows = if pa == pb { q..d } else { 0..d };
                        for r in rows {
                            h[pattern.value_index(pair, pa == pb, r, q)] += hab[(r, q)];
                        }
                    }
                }
            }
        }
        let mut chol = SparseCholesky::analyze(&pattern, SupernodalThreshold::AUTO).ok()?;
        chol.factorize(&pattern, &h).ok()?;
        for r in rhs.iter_mut() {
            chol.solve_in_place(r.as_mut_slice());
        }
        let mut out = Vec::with_capacity(self.fixed_value.len());
        for (v, fixed) in self.fixed_value.iter().enumerate() {
            out.push(match fixed {
                Some(x) => x.clone(),
                None => {
                    let p = pattern.position[self.block[v]?];
                    DMatrix::from_fn(d, self.nrhs, |q, c| rhs[c][pattern.offset[p] + q])
                }
            });
        }
        Some(out)
    }
}

fn scalar(v: f64) -> DMatrix<f64> {
    DMatrix::from_element(1, 1, v)
}

fn chordal_2d(factors: &[FactorEntry], values: &Values, fixed: &[bool]) -> Option<Values> {
    let edges = collect_edges(
        factors,
        values,
        |f| f.factor.as_any().downcast_ref::<BetweenSe2>().map(|b| b.measurement),
        |f| f.factor.as_any().downcast_ref::<PriorSe2>().map(|p| p.measurement),
    )?;
    let n = values.len();
    let pose = |v: usize| *values.variable(v).as_any().downcast_ref::<Se2>().expect("checked kind");
    // Unwrapped tree orientations by BFS from the anchors (fixed variables, then priors).
    let mut adjacency: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    let mut tree: Vec<Option<f64>> = vec![None; n];
    let mut queue = VecDeque::new();
    for v in 0..n {
        if fixed[v] {
            tree[v] = Some(pose(v).theta);
            queue.push_back(v);
        }
    }
    for e in &edges {
        match e.from {
            Some(i) => {
                adjacency[i].push((e.to, e.measurement.theta));
                adjacency[e.to].push((i, -e.measurement.theta));
            }
            None if tree[e.to].is_none() => {
                tree[e.to] = Some(e.measurement.theta);
                queue.push_back(e.to);
            }
            None => {}
        }
    }
    // Breadth-first: shortest paths accumulate the least rotation noise into the unwrapping.
    while let Some(i) = queue.pop_front() {
        let ti = tree[i]?;
        for &(j, d) in &adjacency[i] {
            if tree[j].is_none() {
                tree[j] = Some(ti + d);
                queue.push_back(j);
            }
        }
    }
    let tree: Vec<f64> = tree.into_iter().map(|t| t.unwrap_or(0.0)).collect();
    let fixed_theta: Vec<Option<DMatrix<f64>>> =
        (0..n).map(|v| fixed[v].then(|| scalar(tree[v]))).collect();
    let mut rot = LinearLeastSquares::new(1, 1, &fixed_theta);
    for e in &edges {
        let w = marginal_information(&e.information, 2, 1)?;
        match e.from {
            Some(i) => {
                let k = ((tree[e.to] - tree[i] - e.measurement.theta) / (2.0 * PI)).round();
                let target = e.measurement.theta + 2.0 * PI * k;
                rot.add(&[(e.to, scalar(1.0)), (i, scalar(-1.0))], scalar(-target), w);
            }
            None => {
                let k = ((tree[e.to] - e.measurement.theta) / (2.0 * PI)).round();
                rot.add(&[(e.to, scalar(1.0))], scalar(-(e.measurement.theta + 2.0 * PI * k)), w);
            }
        }
    }
    let theta: Vec<f64> = rot.solve()?.iter().map(|m| m[(0, 0)]).collect();

    let fixed_t: Vec<Option<DMatrix<f64>>> =
        (0..n).map(|v| fixed[v].then(|| DMatrix::from_column_slice(2, 1, &[pose(v).x, pose(v).y]))).collect();
    let mut trans = LinearLeastSquares::new(2, 1, &fixed_t);
    for e in &edges {
        let w = marginal_information(&e.information, 0, 2)?;
        let z = DMatrix::from_column_slice(2, 1, &[e.measurement.x, e.measurement.y]);
        let frame = e.from.map(|i| theta[i]).unwrap_or(0.0);
        let rt = to_dmatrix2(&rotation_matrix_2d(frame).transpose());
        match e.from {
            // R_iᵀ(t_j − t_i) − t_ij
            Some(i) => trans.add(&[(e.to, rt.clone()), (i, -rt)], -z, w),
            None => {
                let target = to_dmatrix2(&rotation_matrix_2d(0.0)) * z;
                trans.add(&[(e.to, rt)], -target, w)
            }
        }
    }
    let t = trans.solve()?;
    let mut out = values.clone();
    for v in 0..n {
        if !fixed[v] {
            out.set(v, &Se2::new(t[v][(0, 0)], t[v][(1, 0)], theta[v]));
        }
    }
    Some(out)
}

fn to_dmatrix2(m: &Matrix2<f64>) -> DMatrix<f64> {
    DMatrix::from_column_slice(2, 2, m.as_slice())
}

fn to_dmatrix3(m: &Matrix3<f64>) -> DMatrix<f64> {
    DMatrix::from_column_slice(3, 3, m.as_slice())
}

fn chordal_3d(factors: &[FactorEntry], values: &Values, fixed: &[bool]) -> Option<Values> {
    let edges = collect_edges(
        factors,
        values,
        |f| f.factor.as_any().downcast_ref::<BetweenSe3>().map(|b| b.measurement),
        |f| f.factor.as_any().downcast_ref::<PriorSe3>().map(|p| p.measurement),
    )?;
    let n = values.len();
    let pose = |v: usize| *values.variable(v).as_any().downcast_ref::<Se3>().expect("checked kind");
    let identity = DMatrix::<f64>::identity(3, 3);
    // Unknown per pose: Rᵀ (its columns are the rows of R), one right-hand side per row.
    let fixed_r: Vec<Option<DMatrix<f64>>> =
        (0..n).map(|v| fixed[v].then(|| to_dmatrix3(&pose(v).rotation_matrix().transpose()))).collect();
    let mut rot = LinearLeastSquares::new(3, 3, &fixed_r);
    let weight = |info: &DMatrix<f64>, start: usize| {
        let trace: f64 = (start..start + 3).map(|k| info[(k, k)]).sum();
        DMatrix::<f64>::identity(3, 3) * (trace / 3.0)
    };
    for e in &edges {
        let rz = to_dmatrix3(&e.measurement.rotation_matrix());
        let w = weight(&e.information, 3);
        match e.from {
            // R_j − R_i R_ij = 0, row k: x_j − R_ijᵀ x_i = 0 with x = (row k of R)ᵀ.
            Some(i) => rot.add(&[(e.to, identity.clone()), (i, -rz.transpose())], DMatrix::zeros(3, 3), w),
            None => rot.add(&[(e.to, identity.clone())], -rz.transpose(), w),
        }
    }
    let rotations: Vec<Matrix3<f64>> = rot
        .solve()?
        .iter()
        .map(|rt| project_to_so3(&Matrix3::from_iterator(rt.iter().copied()).transpose()))
        .collect();

    let fixed_t: Vec<Option<DMatrix<f64>>> =
        (0..n).map(|v| fixed[v].then(|| DMatrix::from_column_slice(3, 1, pose(v).translation.as_slice()))).collect();
    let mut trans = LinearLeastSquares::new(3, 1, &fixed_t);
    for e in &edges {
        let w = weight(&e.information, 0);
        match e.from {
            Some(i) => {
                let rel = rotations[i] * e.measurement.translation;
                trans.add(&[(e.to, identity.clone()), (i, -identity.clone())], -DMatrix::from_column_slice(3, 1, rel.as_slice()), w)
            }
            None => trans.add(
                &[(e.to, identity.clone())],
                -DMatrix::from_column_slice(3, 1, e.measurement.translation.as_slice()),
                w,
            ),
        }
    }
    let t = trans.solve()?;
    let mut out = values.clone();
    for v in 0..n {
        if !fixed[v] {
            let rotation = UnitQuaternion::from_matrix(&rotations[v]);
            out.set(v, &Se3::new(rotation, Vector3::new(t[v][(0, 0)], t[v][(1, 0)], t[v][(2, 0)])));
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
