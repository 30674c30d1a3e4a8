//! What a validated batch is made of: typed parts that cannot fail to apply (see `batch`).

use crate::api::wire::FactorId;
use crate::factors::{Factor, RobustKernel, SqrtInformation};
use crate::problem::{Key, Variable};

pub(crate) struct PreparedFactor {
    pub factor: std::sync::Arc<dyn Factor>,
    pub sqrt_information: SqrtInformation,
    pub robust: Option<RobustKernel>,
    /// A possibly wrong loop closure (`session::outliers`): held out of the problem until the
    /// service decides it fits.
    pub candidate: bool,
}

/// A variable a batch creates, with its (given or predicted) value.
pub(crate) struct NewVariable {
    pub key: Key,
    pub value: Box<dyn Variable>,
    pub fixed: bool,
    /// When the pose was taken (seconds), if the client said.
    pub stamp: Option<f64>,
}

pub(crate) struct PreparedBatch {
    pub variables: Vec<NewVariable>,
    pub factors: Vec<PreparedFactor>,
    pub remove: Vec<FactorId>,
    /// (key, fixed) changes.
    pub fix: Vec<(Key, bool)>,
    pub guesses: Vec<(Key, Box<dyn Variable>)>,
    /// Keys whose value was predicted rather than given.
    pub predicted: Vec<Key>,
    /// Merges the batch completed (`session::robots`), applied after its factors.
    pub merges: Vec<super::robots::Merge>,
}

impl PreparedBatch {
    pub fn factor_count(&self) -> usize {
        self.factors.len()
    }

    /// Whether it changes more than it adds (removals, fixes, guesses, merges): the next solve
    /// is of the whole problem, and no provisional answer knows what it changed.
    pub fn changes_more_than_it_adds(&self) -> bool {
        !self.remove.is_empty()
            || !self.fix.is_empty()
            || !self.guesses.is_empty()
            || !self.merges.is_empty()
    }
}
