//! Times the numeric factorisation of a graph's normal equations at its optimum (the matrix the
//! solver factorises in its last iterations) and one solve with it, and exports the matrix for
//! CHOLMOD comparisons.

use std::fmt::Write as _;
use std::time::Instant;

use faer::sparse::linalg::SupernodalThreshold;

use factord::problem::Problem;
use factord::solver::cholesky::SparseCholesky;
use factord::solver::linearize::{linearize, Scratch, SystemLayout};
use factord::solver::{optimize, SolverOptions};

/// What [`run`] measured: the timings as JSON, and H in Matrix Market form when asked for.
pub struct CholeskyBench {
    pub report: String,
    pub matrix_market: Option<String>,
}

/// `problem` is solved first, then its normal equations are factorised `repeat` times;
/// `with_matrix`: also H (lower triangle, symmetric) as Matrix Market text.
pub fn run(
    problem: &mut Problem,
    repeat: usize,
    with_matrix: bool,
) -> Result<CholeskyBench, Box<dyn std::error::Error>> {
    let summary = optimize(problem, &SolverOptions::default(), &mut |_| {
        std::ops::ControlFlow::Continue(())
    })?;
    let fixed: Vec<bool> = (0..problem.values.len())
        .map(|v| {
            problem.values.is_fixed(v) || summary.used.gauge_fixed.contains(&problem.values.key(v))
        })
        .collect();
    let layout = SystemLayout::new(problem.factors(), &problem.values, &fixed);
    let mut h = vec![0.0; layout.pattern.nnz()];
    let mut b = vec![0.0; layout.n()];
    linearize(
        problem.factors(),
        &problem.values,
        &layout,
        &mut Scratch::new(&layout),
        &mut h,
        &mut b,
    )?;
    let mut report = String::from("{");
    for (name, threshold) in [
        ("auto", SupernodalThreshold::AUTO),
        ("supernodal", SupernodalThreshold::FORCE_SUPERNODAL),
        ("simplicial", SupernodalThreshold::FORCE_SIMPLICIAL),
    ] {
        let t = Instant::now();
        let mut chol = SparseCholesky::analyze(&layout.pattern, threshold)?;
        let analyze = t.elapsed().as_secs_f64();
        let mut runs = Vec::with_capacity(repeat);
        for _ in 0..repeat.max(1) {
            let t = Instant::now();
            chol.factorize(&layout.pattern, &h)
                .map_err(|e| format!("not positive definite at row {}", e.row))?;
            runs.push(t.elapsed().as_secs_f64());
        }
        runs.sort_by(f64::total_cmp);
        let mut solves = Vec::new();
        for _ in 0..repeat.max(1) {
            let mut x = b.clone();
            let t = Instant::now();
            chol.solve_in_place(&mut x);
            solves.push(t.elapsed().as_secs_f64());
        }
        solves.sort_by(f64::total_cmp);
        let _ = write!(
            report,
            "\"{name}\": {{\"kind\": \"{}\", \"numeric_seconds\": {:e}, \"solve_seconds\": {:e}, \"analyze_seconds\": {:e}, \"factor_nnz\": {}}}, ",
            chol.kind(),
            runs[runs.len() / 2],
            solves[solves.len() / 2],
            analyze,
            chol.factor_nnz()
        );
    }
    let _ = write!(
        report,
        "\"system\": \"factord\", \"n\": {}, \"nnz_lower\": {}}}",
        layout.n(),
        layout.pattern.nnz()
    );
    let mut matrix_market = None;
    if with_matrix {
        let p = &layout.pattern;
        let mut text = format!(
            "%%MatrixMarket matrix coordinate real symmetric\n{} {} {}\n",
            p.n,
            p.n,
            p.nnz()
        );
        for c in 0..p.n {
            let column = p.col_ptr[c]..p.col_ptr[c + 1];
            for (&r, &h_rc) in p.row_idx[column.clone()].iter().zip(&h[column]) {
                let _ = writeln!(text, "{} {} {:e}", r + 1, c + 1, h_rc);
            }
        }
        matrix_market = Some(text);
    }
    Ok(CholeskyBench {
        report,
        matrix_market,
    })
}
