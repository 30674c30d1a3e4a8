//! What one incremental update did, reported in the session's Summary and ack (the counterpart
//! of iSAM2's `ISAM2Result`).

use serde::Serialize;

#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct UpdateReport {
    /// Relinearise-refactor-solve rounds this update ran (the first takes the new factors,
    /// later ones only relinearise what still moved more than the threshold).
    pub passes: usize,
    pub new_variables: usize,
    pub new_factors: usize,
    /// Variables whose linearisation point moved (their factors were linearised again).
    pub relinearized_variables: usize,
    /// Variables past the relinearisation threshold that this update left for a later one (a
    /// correction of the whole map: see `UpdateParams::defer_from`).
    pub deferred_variables: usize,
    pub relinearized_factors: usize,
    /// Columns of the factor eliminated again: the touched variables and their ancestors in
    /// the elimination tree, summed over passes.
    pub refactored_columns: usize,
    /// Columns changed by a rank update instead (an update that only adds factors: they are
    /// added along their elimination-tree paths, see `block_factor::rank_update`), summed over
    /// passes.
    pub updated_columns: usize,
    /// Of the refactored columns, those factored in dense fronts (runs that form a clique, the root clique
    /// among them: see `block_factor::front`).
    pub dense_columns: usize,
    /// The whole factor was ordered and eliminated again: its fill had outgrown what a fresh
    /// order gave it (see `whole_order`).
    pub whole_reorder: bool,
    /// Untouched subtrees hanging off the refactored part (their columns were reused).
    pub reused_subtrees: usize,
    /// Columns back-substitution visited, and those whose value changed by more than the
    /// wildfire threshold (the estimate changes published).
    pub solved_columns: usize,
    pub changed_variables: usize,
    /// Scalar nonzeros of the factor after the update, and columns in it.
    pub factor_nnz: usize,
    pub columns: usize,
    /// chi2 of the linearised problem at its solution: Σ chi2 at the linearisation point
    /// minus the decrease the Gauss-Newton step promises (`rᵀr − yᵀy`).
    pub model_chi2: f64,
    /// Largest step left on any variable (max-norm of its tangent), after the last pass.
    pub max_delta: f64,
    pub linearize_seconds: f64,
    pub order_seconds: f64,
    pub factorize_seconds: f64,
    pub solve_seconds: f64,
}
