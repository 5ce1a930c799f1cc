//! What `spintune.SimulationRun` and `spintune.ArraySimulation` share: a
//! core `driver::SimulationRun<P, D>` (run session + simulated device) and
//! its records behind one lock, iterated, controlled and checkpointed from
//! Python with the GIL released while the core computes.

use parking_lot::{Mutex, MutexGuard};
use pyo3::exceptions::{PyRuntimeError, PyStopIteration, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyList;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use spintune::driver::{Halt, Simulated, SimulationRun};
use spintune::protocol::{ControlCommand, IterationRecord};
use spintune::session::Plan;

use crate::convert::{from_py, to_py};
use crate::session::control_error;

/// The run and its records.
pub struct Inner<P, D> {
    pub run: SimulationRun<P, D>,
    pub records: Vec<IterationRecord>,
}

/// A simulated run and its records behind one lock: readers (`status`,
/// `records`, `control()`) from another thread wait at most for the
/// iteration in progress. The lock is released *fairly* (handed to a
/// waiting thread): `run()` takes it again right after each iteration, and
/// with an unfair lock a reader under CPU load could lose every race until
/// the run ended (a `stop` from a watching thread arriving only after
/// 10 000 iterations).
pub struct DrivenRun<P, D> {
    inner: Mutex<Inner<P, D>>,
}

/// A checkpoint: the config, the run (session and device, RNG and lab
/// clock included) and the records so far.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Checkpoint<C, R, V> {
    config: C,
    run: R,
    records: V,
}

impl<P, D> DrivenRun<P, D>
where
    P: Plan + Send,
    D: Simulated + Send,
    SimulationRun<P, D>: Serialize + DeserializeOwned,
{
    /// A run with no records yet.
    pub fn new(run: SimulationRun<P, D>) -> Self {
        Self {
            inner: Mutex::new(Inner {
                run,
                records: Vec::new(),
            }),
        }
    }

    /// Run `f` with the lock, the GIL released (so other Python threads, and
    /// readers of this run, go on; no lock is held while the GIL is taken).
    /// The lock goes to a thread waiting for it, if any, when `f` returns.
    pub fn with<T: Send>(&self, py: Python<'_>, f: impl FnOnce(&mut Inner<P, D>) -> T + Send) -> T {
        py.detach(|| {
            let mut inner = self.inner.lock();
            let out = f(&mut inner);
            MutexGuard::unlock_fair(inner);
            out
        })
    }

    /// The next iteration's record (kept), `None` when the run is over or
    /// paused; a fault is a `RuntimeError`.
    fn next_record(&self, py: Python<'_>) -> PyResult<Option<IterationRecord>> {
        let result = self.with(py, |inner| {
            let r = inner.run.next_iteration();
            if let Ok(Some(record)) = &r {
                inner.records.push(record.clone());
            }
            r
        });
        match result {
            Ok(Some(record)) => Ok(Some(record)),
            Ok(None) | Err(Halt::Paused) => Ok(None),
            Err(Halt::Fault(f)) => Err(PyRuntimeError::new_err(format!(
                "the simulated run faulted: {f} (resume with control({{\"action\": \"resume\"}}))"
            ))),
            Err(e @ Halt::Session(_)) => Err(PyRuntimeError::new_err(e.to_string())),
        }
    }

    /// `__next__`: the next record (dict), `StopIteration` when over or paused.
    pub fn next_py<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        match self.next_record(py)? {
            Some(record) => to_py(py, &record),
            None => Err(PyStopIteration::new_err(())),
        }
    }

    /// At most `max_iterations` more iterations (`None`: until over or
    /// paused), then every record so far.
    pub fn run<'py>(
        &self,
        py: Python<'py>,
        max_iterations: Option<u64>,
    ) -> PyResult<Bound<'py, PyList>> {
        let mut done = 0u64;
        while max_iterations.is_none_or(|m| done < m) {
            if self.next_record(py)?.is_none() {
                break;
            }
            done += 1;
            py.check_signals()?;
        }
        self.records(py)
    }

    /// Every record so far, oldest first (list of dicts).
    pub fn records<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let records = self.with(py, |inner| inner.records.clone());
        let list = PyList::empty(py);
        for r in &records {
            list.append(to_py(py, r)?)?;
        }
        Ok(list)
    }

    /// The session's status (dict).
    pub fn status<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let status = self.with(py, |inner| inner.run.session().status());
        to_py(py, &status)
    }

    /// Apply a control command (dict); the new status (dict).
    pub fn control<'py>(
        &self,
        py: Python<'py>,
        command: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let command: ControlCommand = from_py(command, "control command")?;
        let status = self
            .with(py, |inner| inner.run.control(&command))
            .map_err(control_error)?;
        to_py(py, &status)
    }

    /// Number of records and the status' name (for `__repr__`).
    pub fn summary(&self, py: Python<'_>) -> (usize, &'static str) {
        self.with(py, |inner| {
            (inner.records.len(), inner.run.session().status().name())
        })
    }

    /// The config, the run and the records as one JSON string.
    pub fn checkpoint<C: Serialize + Sync>(&self, py: Python<'_>, config: &C) -> PyResult<String> {
        self.with(py, |inner| {
            serde_json::to_string(&Checkpoint {
                config,
                run: &inner.run,
                records: &inner.records,
            })
        })
        .map_err(|e| PyRuntimeError::new_err(format!("cannot serialize the run: {e}")))
    }

    /// The config and the run of [`DrivenRun::checkpoint`]'s string.
    pub fn restore<C: DeserializeOwned + Send>(
        py: Python<'_>,
        checkpoint: &str,
    ) -> PyResult<(C, Self)> {
        let c: Checkpoint<C, SimulationRun<P, D>, Vec<IterationRecord>> = py
            .detach(|| {
                let de = &mut serde_json::Deserializer::from_str(checkpoint);
                serde_path_to_error::deserialize(de)
            })
            .map_err(|e| PyValueError::new_err(format!("invalid checkpoint: {e}")))?;
        let run = Self {
            inner: Mutex::new(Inner {
                run: c.run,
                records: c.records,
            }),
        };
        Ok((c.config, run))
    }
}

/// `__reduce__` of a run class: `(cls.restore, (checkpoint,))`.
pub fn reduce<'py>(
    slf: &Bound<'py, PyAny>,
    checkpoint: String,
) -> PyResult<(Bound<'py, PyAny>, (String,))> {
    Ok((slf.get_type().getattr("restore")?, (checkpoint,)))
}
