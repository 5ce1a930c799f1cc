//! Why a run's control action or lookup failed ([`RunError`], mapped to an
//! HTTP status by the server), and the store failures a caller tells apart.

use crate::store::StoreError;

/// Why a control action or lookup failed; maps to an HTTP status.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunError {
    /// No such run (404).
    #[error("no run with id {0}")]
    NotFound(u64),
    /// The action does not apply in the run's present state (409).
    #[error("{0}")]
    Conflict(String),
    /// The command's content is invalid (400 / 422), e.g. an unknown parameter.
    #[error("{0}")]
    Invalid(String),
    /// The store failed (500; a stale task generation ends that task).
    #[error("{0}")]
    Store(StoreErrorKind),
    /// Internal failure (500).
    #[error("{0}")]
    Internal(String),
}

/// The store failures a caller distinguishes.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StoreErrorKind {
    /// Another task drives the run now.
    #[error("{0}")]
    Stale(String),
    /// Anything else.
    #[error("{0}")]
    Other(String),
}

impl From<StoreError> for RunError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::NotFound(id) => RunError::NotFound(id),
            e @ StoreError::Stale { .. } => RunError::Store(StoreErrorKind::Stale(e.to_string())),
            e => RunError::Store(StoreErrorKind::Other(e.to_string())),
        }
    }
}

impl RunError {
    /// Whether this is a stale-generation refusal (another task drives the run).
    pub fn is_stale(&self) -> bool {
        matches!(self, RunError::Store(StoreErrorKind::Stale(_)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stale_store_errors_are_told_apart() {
        let e = RunError::from(StoreError::Stale {
            run: 1,
            generation: 1,
            current: 2,
        });
        assert!(e.is_stale());
        assert!(!RunError::from(StoreError::NotFound(1)).is_stale());
    }
}
