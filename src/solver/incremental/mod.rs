//! The incremental engine of a session: a block Cholesky factor that lives between updates,
//! refactored only along the elimination-tree paths an update touches, with the touched part
//! reordered so that new variables stay last, and relinearisation only of what moved.

mod dense;
mod linearized;
mod report;

pub use report::UpdateReport;
