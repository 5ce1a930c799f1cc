//! The checkpoint of a run: its schema ([`CHECKPOINT_VERSION`]), the
//! migration of older releases' checkpoints (tuner only, no version) and the
//! check that a stored checkpoint belongs to the run's config.

use serde::{Deserialize, Serialize};
use serde_json::Value;
use spintune::session::{RunSession, SessionConfig};
use spintune::tuner::array_run::ArrayRun;
use spintune::tuner::Tuner;

use super::any_session::AnySession;
use super::error::RunError;
use crate::config::RunConfig;

/// Schema version of [`Checkpoint`] written by this release. Checkpoints
/// without a version were written by older releases (read as version 1).
pub const CHECKPOINT_VERSION: u32 = 2;

fn legacy_checkpoint_version() -> u32 {
    1
}

/// Everything needed to continue a run: stored after every iteration.
#[derive(Debug, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Schema version ([`CHECKPOINT_VERSION`]); checked on load.
    #[serde(default = "legacy_checkpoint_version")]
    pub version: u32,
    /// The session's complete state (tuner, mode, deferred targets).
    #[serde(default)]
    pub session: Option<RunSession>,
    /// An array run's session (instead of `session`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub array_session: Option<RunSession<ArrayRun>>,
    /// A checkpoint written before run sessions existed holds the tuner only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tuner: Option<Tuner>,
    /// The device's state (`null` for devices without restorable state).
    pub device: Value,
}

impl Checkpoint {
    /// A checkpoint of this release.
    pub fn new(session: AnySession, device: Value) -> Self {
        let (cell, array) = match session {
            AnySession::Cell(s) => (Some(*s), None),
            AnySession::Array(s) => (None, Some(*s)),
        };
        Self {
            version: CHECKPOINT_VERSION,
            session: cell,
            array_session: array,
            tuner: None,
            device,
        }
    }

    /// Parse and check a stored checkpoint of run `id`: malformed JSON, an
    /// unknown schema version or a state that does not belong to the run's
    /// config (other gates or limits: invariant 5 rests on them) is an error
    /// naming the problem, never a panic.
    pub fn load(id: u64, json: &str, config: &RunConfig) -> Result<Self, RunError> {
        let unusable = |why: String| {
            RunError::Conflict(format!(
                "run {id} cannot continue: its stored checkpoint {why}"
            ))
        };
        let raw: Value =
            serde_json::from_str(json).map_err(|e| unusable(format!("is not JSON ({e})")))?;
        let version = match raw.get("version") {
            None => legacy_checkpoint_version(),
            Some(v) => v
                .as_u64()
                .and_then(|v| u32::try_from(v).ok())
                .ok_or_else(|| unusable(format!("has an invalid schema version {v}")))?,
        };
        if version == 0 || version > CHECKPOINT_VERSION {
            return Err(unusable(format!(
                "has schema version {version}; this server reads versions 1 to {CHECKPOINT_VERSION}"
            )));
        }
        let cp: Checkpoint = serde_path_to_error::deserialize(raw)
            .map_err(|e| unusable(format!("is malformed at `{}`: {}", e.path(), e.inner())))?;
        if let Some(array) = &config.array {
            let Some(session) = &cp.array_session else {
                return Err(unusable("holds no array session for this array run".into()));
            };
            use spintune::session::Plan;
            let want = array.gates().map_err(|e| {
                unusable(format!("belongs to a config whose array is invalid: {e}"))
            })?;
            check_gates(&want, session.tuner().gate_specs()).map_err(unusable)?;
            return Ok(cp);
        }
        if cp.array_session.is_some() {
            return Err(unusable(
                "holds an array session, but the run is not an array".into(),
            ));
        }
        let tuner = match (&cp.session, &cp.tuner) {
            (Some(s), _) => s.tuner(),
            (None, Some(t)) => t,
            (None, None) => return Err(unusable("holds neither a session nor a tuner".into())),
        };
        check_gates(&config.simulation.tuner.gates, &tuner.config().gates).map_err(unusable)?;
        if let Some((gate, v)) = tuner.voltages_mv().iter().find(|(_, v)| !v.is_finite()) {
            return Err(unusable(format!(
                "holds a non-finite voltage {v} for {gate}"
            )));
        }
        Ok(cp)
    }

    /// The session to continue from (an old tuner-only checkpoint gets a
    /// fresh session around its tuner).
    pub fn into_session(self, config: SessionConfig) -> Result<(AnySession, Value), RunError> {
        match (self.session, self.array_session, self.tuner) {
            (Some(s), _, _) => Ok((AnySession::Cell(Box::new(s)), self.device)),
            (None, Some(s), _) => Ok((AnySession::Array(Box::new(s)), self.device)),
            (None, None, Some(t)) => Ok((
                AnySession::Cell(Box::new(RunSession::from_tuner(t, config))),
                self.device,
            )),
            (None, None, None) => Err(RunError::Internal(
                "checkpoint holds neither a session nor a tuner".into(),
            )),
        }
    }
}

/// `Err` unless the stored gates are the config's, with the same limits
/// (invariant 5 rests on them).
fn check_gates(
    want: &[spintune::safety::GateSpec],
    have: &[spintune::safety::GateSpec],
) -> Result<(), String> {
    let same = want.len() == have.len()
        && want.iter().zip(have).all(|(a, b)| {
            a.name == b.name
                && a.min_mv == b.min_mv
                && a.max_mv == b.max_mv
                && a.max_step_mv == b.max_step_mv
        });
    if !same {
        return Err("has other gates or gate limits than the run's config".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use spintune::protocol::RunStatus;

    #[test]
    fn a_tuner_only_checkpoint_of_an_older_release_still_resumes() {
        let cfg = spintune::driver::SimulationConfig::paper_default();
        let tuner = Tuner::new(cfg.tuner).unwrap();
        let old = serde_json::json!({ "tuner": tuner, "device": null });
        let cp: Checkpoint = serde_json::from_value(old).unwrap();
        let (session, _) = cp.into_session(SessionConfig::default()).unwrap();
        let AnySession::Cell(session) = session else {
            panic!("a single-cell checkpoint")
        };
        assert_eq!(session.tuner().iteration(), 0);
        assert_eq!(session.status(), RunStatus::Running);
    }
}
