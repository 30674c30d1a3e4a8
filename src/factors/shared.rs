//! One factor in two places: a session with a latency budget keeps its recent factors in the
//! problem (which a worker takes away for the exact solve) and beside it, for the provisional
//! answers given meanwhile (`session::provisional`). A factor is not `Clone` (user-defined ones
//! hold compiled tapes), so both hold it through an `Arc`.

use std::any::Any;
use std::sync::Arc;

use super::{EvaluationError, Factor};
use crate::variables::{Key, Variable};

/// A factor behind an `Arc`, answering exactly as the factor itself (`as_any` included, so
/// downcasts to the concrete factor still work).
#[derive(Clone, Debug)]
pub struct SharedFactor(pub Arc<dyn Factor>);

impl Factor for SharedFactor {
    fn name(&self) -> &str {
        self.0.name()
    }

    fn keys(&self) -> &[Key] {
        self.0.keys()
    }

    fn residual_dim(&self) -> usize {
        self.0.residual_dim()
    }

    fn variable_kinds(&self) -> &[&'static str] {
        self.0.variable_kinds()
    }

    fn evaluate(
        &self,
        variables: &[&dyn Variable],
        error: &mut [f64],
        jacobian: Option<&mut [f64]>,
    ) -> Result<(), EvaluationError> {
        self.0.evaluate(variables, error, jacobian)
    }

    fn as_any(&self) -> &dyn Any {
        self.0.as_any()
    }

    fn predict(&self, known: &[Option<&dyn Variable>], target: usize) -> Option<Box<dyn Variable>> {
        self.0.predict(known, target)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::factors::between_se2::BetweenSe2;
    use crate::geometry::Se2;

    #[test]
    fn answers_as_the_factor_it_shares() {
        let inner: Arc<dyn Factor> = Arc::new(BetweenSe2::new(1, 2, Se2::new(1.0, 0.5, 0.2)));
        let shared = SharedFactor(Arc::clone(&inner));
        assert_eq!(shared.name(), inner.name());
        assert_eq!(shared.keys(), &[1, 2]);
        assert!(shared.as_any().downcast_ref::<BetweenSe2>().is_some());
        let (a, b) = (Se2::new(0.0, 0.0, 0.0), Se2::new(1.0, 0.4, 0.25));
        let mut e1 = [0.0; 3];
        let mut e2 = [0.0; 3];
        inner.evaluate(&[&a, &b], &mut e1, None).unwrap();
        shared.evaluate(&[&a, &b], &mut e2, None).unwrap();
        assert_eq!(e1, e2);
        let predicted = shared
            .predict(&[Some(&a), None], 1)
            .expect("odometry predicts");
        assert!(predicted.as_any().downcast_ref::<Se2>().is_some());
    }
}
