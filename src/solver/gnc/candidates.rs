//! Which factors may be wrong. Odometry (a factor between consecutive keys of one sequence) and
//! priors are trusted; a factor between two poses that are not consecutive is a loop closure,
//! found by place recognition, and place recognition is wrong a few percent of the time.

use crate::problem::Problem;

/// `true` for every factor between two variables whose keys are not consecutive (a loop
/// closure); `false` for odometry, priors and factors on three or more variables.
pub fn loop_closures(problem: &Problem) -> Vec<bool> {
    problem
        .factors()
        .iter()
        .map(|f| match f.variables() {
            [a, b] => {
                let (ka, kb) = (problem.values.key(*a), problem.values.key(*b));
                ka.abs_diff(kb) != 1
            }
            _ => false,
        })
        .collect()
}

/// Whether the problem has any loop closure ([`loop_closures`]) at all.
pub fn has_loop_closures(problem: &Problem) -> bool {
    loop_closures(problem).into_iter().any(|c| c)
}
