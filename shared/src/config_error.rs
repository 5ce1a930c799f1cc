//! [`ConfigError`]: the one error of the config boundary (tuner, simulated
//! device, tolerances, and the backend's driver settings).
//!
//! Every validation function returns the path of the offending field
//! *relative to the value it checks* (`scans.load_points` for a
//! [`crate::sim::DeviceConfig`], `relative` for a
//! [`crate::parameter::Tolerance`]); the caller that knows where that value
//! sits prefixes it with [`ConfigError::within`] (`device.scans.load_points`,
//! `tolerances.w.relative`).

/// A config value that does not make sense, with the path of the field.
///
/// ```
/// use spintune::ConfigError;
/// let e = ConfigError::new("channels.SB", "channel numbers start at 1").within("scpi");
/// assert_eq!(e.field, "scpi.channels.SB");
/// assert_eq!(
///     e.to_string(),
///     "invalid config at `scpi.channels.SB`: channel numbers start at 1"
/// );
/// ```
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}", self.describe())]
pub struct ConfigError {
    /// Dotted path of the offending field, e.g. `tuner.levels[0].gates[2]`.
    pub field: String,
    /// What is wrong with it.
    pub message: String,
}

impl ConfigError {
    /// New error for `field`.
    pub fn new(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            message: message.into(),
        }
    }

    /// `Ok` if `ok`, else an error for `field` saying `value` is out of its
    /// bounds (the bounds are stated where the field is documented).
    ///
    /// ```
    /// use spintune::ConfigError;
    /// assert!(ConfigError::check(true, "line_rounds", 1).is_ok());
    /// let e = ConfigError::check(false, "line_rounds", 9).unwrap_err();
    /// assert_eq!(e.to_string(), "invalid config at `line_rounds`: 9 out of bounds");
    /// ```
    pub fn check(ok: bool, field: &str, value: impl std::fmt::Display) -> Result<(), Self> {
        if ok {
            Ok(())
        } else {
            Err(Self::new(field, format!("{value} out of bounds")))
        }
    }

    /// Prefix the field path with `outer` (e.g. `tuner`). An empty field
    /// (the value as a whole) becomes `outer` itself.
    pub fn within(mut self, outer: &str) -> Self {
        self.field = if self.field.is_empty() {
            outer.to_string()
        } else if outer.is_empty() {
            self.field
        } else {
            format!("{outer}.{}", self.field)
        };
        self
    }

    /// `invalid config at `field`: message` (`invalid config: message` for
    /// the config as a whole, an empty field).
    fn describe(&self) -> String {
        if self.field.is_empty() {
            format!("invalid config: {}", self.message)
        } else {
            format!("invalid config at `{}`: {}", self.field, self.message)
        }
    }

    /// `` `field` message``: the error as one clause, for embedding in
    /// another message (e.g. a refused control command).
    pub fn clause(&self) -> String {
        format!("`{}` {}", self.field, self.message)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn within_prefixes_dotted_paths() {
        let e = ConfigError::new("levels[0].solver.max_step_mv", "must be > 0")
            .within("tuner")
            .within("run");
        assert_eq!(e.field, "run.tuner.levels[0].solver.max_step_mv");
        assert_eq!(e.message, "must be > 0");
        assert_eq!(
            e.to_string(),
            "invalid config at `run.tuner.levels[0].solver.max_step_mv`: must be > 0"
        );
    }

    #[test]
    fn within_handles_empty_paths() {
        assert_eq!(ConfigError::new("", "x").within("scpi").field, "scpi");
        assert_eq!(ConfigError::new("a.b", "x").within("").field, "a.b");
    }

    #[test]
    fn clause_names_field_and_problem() {
        let e = ConfigError::new("relative", "must be finite and non-negative, got -1");
        assert_eq!(
            e.clause(),
            "`relative` must be finite and non-negative, got -1"
        );
    }
}
