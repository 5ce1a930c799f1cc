//! Plain, serializable messages: what the tuner asks of a device, what the
//! device answers, and the per-iteration record that is stored and streamed.
//! Nothing else crosses a process boundary (ARCHITECTURE.md, invariant 3).
//!
//! Units are in the field names: `_mv` millivolts, `_s` seconds, parameter
//! values in the unit of their [`crate::parameter::ParameterSpec`].

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// Version of the wire format; bumped on any incompatible change.
///
/// Version 4 added arrays of double-dot cells: [`Request::Batch`] and
/// [`Response::Batch`] (requests run at the same time), scans that name
/// their cell ([`ScanRequest::cell`]) and records whose parameters and
/// gates carry the cell prefix `c{k}.` (e.g. `c3.t_sr`, `c3.SB`). A
/// version-3 lab script would receive a batch it cannot answer, so it is
/// refused when it connects, like every other version.
///
/// Within version 3, alerts were added without a bump: a viewer that sends
/// `subscribe` with `alerts: true` is also sent [`ServerMessage::Alert`]
/// frames; a version-3 client that does not ask never sees one.
///
/// Version 2 added [`Request::ReadVoltages`], the typed [`RunStatus::Faulted`]
/// and [`RunStatus::Stepping`] states and typed [`TunerEvent`]s. Version 3
/// added the fault policy: [`FaultKind::Disconnected`] and
/// [`FaultKind::Moved`], [`Fault::cleared_by`] and [`Fault::moved`],
/// [`ControlCommand::AcceptPositions`] and [`Response::Error`]'s `cause`. A
/// client states the version it speaks when it connects (the server refuses
/// any other with an error naming both versions).
pub const PROTOCOL_VERSION: u32 = 4;

/// Why a message that crossed a boundary (a WebSocket frame, an HTTP body, a
/// lab bridge's answer, a device's evaluated scan) was refused. The text
/// names the field and, where there is one, the offending value.
///
/// ```
/// use spintune::protocol::ProtocolError;
/// let e = ProtocolError::malformed("command.target", "invalid type: string \"high\", expected f64");
/// assert_eq!(
///     e.to_string(),
///     "malformed message at `command.target`: invalid type: string \"high\", expected f64"
/// );
/// ```
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProtocolError {
    /// Not JSON, or not of the expected shape (wrong type, unknown variant,
    /// missing key).
    #[error(
        "malformed message{}: {message}",
        field.as_ref().map(|f| format!(" at `{f}`")).unwrap_or_default()
    )]
    Malformed {
        /// Path of the offending field; `None` for the message as a whole.
        field: Option<String>,
        /// What the parser objected to.
        message: String,
    },
    /// A key the message type does not have.
    #[error("malformed message: unknown field `{field}`")]
    UnknownField {
        /// Path of the key, e.g. `command.extra`.
        field: String,
    },
    /// A number that must be finite is NaN or infinite.
    #[error("{field} must be a finite number, got {value}")]
    NotFinite {
        /// What the number is, e.g. `target of "w"`.
        field: String,
        /// The value received.
        value: f64,
    },
    /// A variance that is negative, NaN or infinite.
    #[error("{field} must be finite and non-negative, got {value}")]
    InvalidVariance {
        /// What the variance is, e.g. `variance of "w"`.
        field: String,
        /// The value received.
        value: f64,
    },
    /// A tolerance that is negative, NaN or infinite.
    #[error("tolerance of {parameter:?}: {}", error.clause())]
    InvalidTolerance {
        /// The parameter whose tolerance it is.
        parameter: String,
        /// The tolerance's own validation error (its field: `absolute` or `relative`).
        error: crate::config_error::ConfigError,
    },
}

impl ProtocolError {
    /// A [`ProtocolError::Malformed`] at `path`, as a JSON path printer
    /// writes it (`""` or `"."`: the message as a whole).
    pub fn malformed(path: &str, message: impl std::fmt::Display) -> Self {
        let field = (!path.is_empty() && path != ".").then(|| path.to_string());
        Self::Malformed {
            field,
            message: message.to_string(),
        }
    }
}

/// The measurements a device can be asked for (defined next to
/// [`crate::parameter::ParameterSpec`], which names the scan of each
/// parameter).
pub use crate::parameter::ScanKind;

/// A 1-D sweep of one gate, mV.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sweep {
    /// Swept gate.
    pub gate: String,
    /// Start, mV.
    pub from_mv: f64,
    /// End, mV.
    pub to_mv: f64,
    /// Number of points (≥ 2).
    pub points: usize,
}

/// Ask the device to run one scan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanRequest {
    /// What to measure.
    pub kind: ScanKind,
    /// For [`ScanKind::SensingDot`]: the sweep. Other kinds use the device's own settings.
    #[serde(default)]
    pub sweep: Option<Sweep>,
    /// Which cell of an array the scan belongs to (`sim::array`; 0-based,
    /// below `sim::array::MAX_CELLS`). `None` for a single double dot: then
    /// the field is left out of the JSON, so every single-cell message is
    /// byte-identical to protocol 3 without it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell: Option<u32>,
}

/// One trace of raw data: `y` against `x`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Trace {
    /// What the trace is, e.g. `"RFA sweep"` or `"fit"`.
    pub label: String,
    /// Abscissa values.
    pub x: Vec<f64>,
    /// Ordinate values (same length as `x`).
    pub y: Vec<f64>,
}

/// Raw data of one scan, as a device returns it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawScan {
    /// Which scan this is.
    pub kind: ScanKind,
    /// Abscissa label with unit, e.g. `"detuning ε (mV)"`, `"wait time (ns)"`.
    pub x_label: String,
    /// Ordinate label with unit, e.g. `"sensor signal (a.u.)"`.
    pub y_label: String,
    /// One or more traces (the chemical-potential scan has one per line).
    pub traces: Vec<Trace>,
}

/// A measured parameter value with its variance (unit², never NaN or negative
/// once accepted by the tuner).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParameterValue {
    /// Parameter name, e.g. `"w"`.
    pub name: String,
    /// Value in the parameter's unit.
    pub value: f64,
    /// Variance `δp²` in the parameter's unit squared.
    pub variance: f64,
}

impl ParameterValue {
    /// `Err` naming the parameter and the value if value or variance is
    /// NaN/∞ or the variance negative.
    ///
    /// ```
    /// use spintune::protocol::ParameterValue;
    /// let v = ParameterValue { name: "w".into(), value: 210.0, variance: -1.0 };
    /// assert_eq!(
    ///     v.validate().unwrap_err().to_string(),
    ///     "variance of \"w\" must be finite and non-negative, got -1"
    /// );
    /// ```
    pub fn validate(&self) -> Result<(), ProtocolError> {
        if !self.value.is_finite() {
            return Err(ProtocolError::NotFinite {
                field: format!("value of {:?}", self.name),
                value: self.value,
            });
        }
        if !(self.variance.is_finite() && self.variance >= 0.0) {
            return Err(ProtocolError::InvalidVariance {
                field: format!("variance of {:?}", self.name),
                value: self.variance,
            });
        }
        Ok(())
    }
}

/// What a scan produced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ScanOutcome {
    /// Raw traces; the tuner fits them with [`crate::fit::evaluate_with`]
    /// and its config's `fit_references`.
    Raw {
        /// The data.
        scan: RawScan,
    },
    /// Already-evaluated parameters (e.g. from a lab's own analysis).
    Evaluated {
        /// The values.
        values: Vec<ParameterValue>,
    },
    /// The measurement could not be made.
    Failed {
        /// Why.
        reason: String,
    },
}

/// What the tuner asks of a device. Produced only by the tuner, executed by a driver.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "request", rename_all = "snake_case")]
pub enum Request {
    /// Set these gates (absolute voltages, mV). Already within limits and step limits.
    SetVoltages {
        /// Gate → voltage, mV.
        voltages_mv: BTreeMap<String, f64>,
    },
    /// Run a scan.
    Measure {
        /// Which scan and how.
        scan: ScanRequest,
    },
    /// Read back the present output of these gates without changing them
    /// (answered by [`Response::VoltagesRead`]). The run session asks this on
    /// connect, on every resume and after a sweep, and checks the next step
    /// against the answer, never against its own plan.
    ReadVoltages {
        /// Gates to read.
        gates: Vec<String>,
    },
    /// Simulator only: the true Jacobian of `parameters` w.r.t. `gates` (unit/mV)
    /// and the true parameter values, for the oracle baseline.
    TrueJacobian {
        /// Gates (columns).
        gates: Vec<String>,
        /// Parameter names (rows).
        parameters: Vec<String>,
    },
    /// Let `seconds` of lab time pass without touching the device (keep
    /// mode's idle time between checks; answered by [`Response::Waited`]).
    /// A simulator advances its clock; a lab driver sleeps. At most
    /// [`MAX_WAIT_SECONDS`]; a longer idle is several waits.
    Wait {
        /// Lab time to let pass, s (0 < seconds ≤ [`MAX_WAIT_SECONDS`]).
        seconds: f64,
    },
    /// Run these requests "at the same time" (an array of cells: scans of
    /// cells in different readout groups run in parallel, the lab clock
    /// charges the longest group); answered by [`Response::Batch`] with one
    /// answer per request, in order. At most [`MAX_BATCH_REQUESTS`]
    /// requests, none of them a batch. Protocol version 4.
    Batch {
        /// The requests, in order.
        requests: Vec<Request>,
    },
}

/// The most requests in one [`Request::Batch`] (16 cells × a few requests
/// each fit many times over); a longer batch is refused.
pub const MAX_BATCH_REQUESTS: usize = 1024;

/// The longest single [`Request::Wait`], s (10 min): a keep run's idle
/// time is cut into waits no longer than this, so a record of progress
/// and a checkpoint follow at least this often in lab time.
pub const MAX_WAIT_SECONDS: f64 = 600.0;

/// The device's answer to a [`Request`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "response", rename_all = "snake_case")]
pub enum Response {
    /// Voltages were applied; the read-back values (mV).
    VoltagesSet {
        /// Gate → read-back voltage, mV.
        voltages_mv: BTreeMap<String, f64>,
        /// Lab time the operation took, s.
        lab_seconds: f64,
    },
    /// Answer to [`Request::ReadVoltages`]: the instrument's present output
    /// of exactly the requested gates, mV.
    VoltagesRead {
        /// Gate → present voltage, mV.
        voltages_mv: BTreeMap<String, f64>,
        /// Lab time the read took, s.
        #[serde(default)]
        lab_seconds: f64,
    },
    /// A scan finished (or failed).
    Scanned {
        /// Its result.
        outcome: ScanOutcome,
        /// Lab time the scan took, s.
        lab_seconds: f64,
    },
    /// Answer to [`Request::TrueJacobian`].
    TrueJacobian {
        /// True parameter values (rows' order).
        values: Vec<f64>,
        /// Row-major m×n Jacobian, unit/mV.
        jacobian: Vec<Vec<f64>>,
    },
    /// Answer to [`Request::Wait`]: the lab time that passed, s.
    Waited {
        /// Lab time that passed, s.
        lab_seconds: f64,
    },
    /// Answer to [`Request::Batch`]: one answer per request, in order.
    Batch {
        /// The answers.
        responses: Vec<Response>,
        /// Lab time the whole batch took, s (the longest readout group's).
        lab_seconds: f64,
    },
    /// The device could not execute the request.
    Error {
        /// Why.
        message: String,
        /// Whether the device was unreachable (a fault that may clear when it
        /// reconnects) or reported a problem a person must look at (the
        /// default, also when a lab bridge omits it).
        #[serde(default, skip_serializing_if = "ErrorCause::is_instrument")]
        cause: ErrorCause,
    },
}

impl Response {
    /// The lab time this answer says its request took, s (0 for an answer
    /// without one, such as an error, and for a non-finite or negative
    /// report).
    ///
    /// ```
    /// use spintune::protocol::Response;
    /// assert_eq!(Response::Waited { lab_seconds: 60.0 }.lab_seconds(), 60.0);
    /// assert_eq!(Response::error("no").lab_seconds(), 0.0);
    /// assert_eq!(Response::Waited { lab_seconds: f64::NAN }.lab_seconds(), 0.0);
    /// ```
    pub fn lab_seconds(&self) -> f64 {
        let s = match self {
            Response::VoltagesSet { lab_seconds, .. }
            | Response::VoltagesRead { lab_seconds, .. }
            | Response::Scanned { lab_seconds, .. }
            | Response::Waited { lab_seconds }
            | Response::Batch { lab_seconds, .. } => *lab_seconds,
            Response::TrueJacobian { .. } | Response::Error { .. } => 0.0,
        };
        if s.is_finite() && s > 0.0 {
            s
        } else {
            0.0
        }
    }

    /// A [`Response::Error`] that needs a person ([`ErrorCause::Instrument`]).
    ///
    /// ```
    /// use spintune::protocol::{ErrorCause, Response};
    /// let r = Response::error("leakage on SB");
    /// assert_eq!(serde_json::to_string(&r).unwrap(), r#"{"response":"error","message":"leakage on SB"}"#);
    /// assert!(matches!(r, Response::Error { cause: ErrorCause::Instrument, .. }));
    /// ```
    pub fn error(message: impl Into<String>) -> Self {
        Response::Error {
            message: message.into(),
            cause: ErrorCause::Instrument,
        }
    }

    /// A [`Response::Error`] for a device that could not be reached
    /// ([`ErrorCause::Disconnected`]): the fault may clear when it reconnects.
    pub fn disconnected(message: impl Into<String>) -> Self {
        Response::Error {
            message: message.into(),
            cause: ErrorCause::Disconnected,
        }
    }
}

/// Why a device answered [`Response::Error`]; decides the [`FaultKind`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCause {
    /// The instrument (or its driver) reported a problem: an error, a
    /// leakage current, a read-back that does not match. Needs a person.
    #[default]
    Instrument,
    /// The device could not be reached (the lab bridge is not connected,
    /// disconnected or did not answer in time). Nothing is known to be wrong
    /// with the instrument; the fault clears when the device reconnects.
    Disconnected,
}

impl ErrorCause {
    /// Whether this is the default, [`ErrorCause::Instrument`].
    pub fn is_instrument(&self) -> bool {
        *self == ErrorCause::Instrument
    }
}

/// One parameter in an [`IterationRecord`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParameterReport {
    /// Name.
    pub name: String,
    /// Unit.
    pub unit: String,
    /// Measured value, if the measurement succeeded.
    pub value: Option<f64>,
    /// Standard deviation δp of the measurement.
    pub std: Option<f64>,
    /// Target, if any.
    pub target: Option<f64>,
    /// Half-width of the tolerance band around the target (parameter units).
    pub tolerance: Option<f64>,
}

/// One estimated Jacobian row in an [`IterationRecord`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GradientReport {
    /// Parameter name.
    pub parameter: String,
    /// Unit of the gradient, e.g. `"ns/mV"` (or `"1/mV"` in log space).
    pub unit: String,
    /// Gradient over the level's gates.
    pub gradient: Vec<f64>,
    /// Covariance (row-major), if the estimator has one.
    pub covariance: Option<Vec<Vec<f64>>>,
}

/// A scan with its fit, for display.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanReport {
    /// The raw data.
    pub raw: RawScan,
    /// Fitted curves over the same axes (empty if the fit failed).
    pub fit: Vec<Trace>,
}

/// Everything about one top-level iteration: stored, streamed, exported.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IterationRecord {
    /// Iteration number k (0 = first measurement after initialisation).
    pub iteration: u64,
    /// All gate voltages at the time of the measurement, mV.
    pub voltages_mv: BTreeMap<String, f64>,
    /// The top level's gates, in gradient order.
    pub gates: Vec<String>,
    /// Measured parameters.
    pub parameters: Vec<ParameterReport>,
    /// Gradient estimates after this iteration's update.
    pub gradients: Vec<GradientReport>,
    /// Step decided in this iteration over `gates`, mV (zeros if none).
    pub step_mv: Vec<f64>,
    /// Every targeted parameter is inside its band.
    pub tuned: bool,
    /// Cumulative lab time since the run started, s.
    pub lab_seconds: f64,
    /// Cumulative number of scans per kind.
    pub scan_counts: BTreeMap<ScanKind, u64>,
    /// Cumulative number of failed or rejected evaluations.
    pub failed_evaluations: u64,
    /// Latest scans of the top level's parameters, with their fits.
    pub scans: Vec<ScanReport>,
    /// Notable events of this iteration (gated outliers, failed fits, clipped steps).
    pub events: Vec<TunerEvent>,
    /// Keep mode (issue 23): what this iteration was and when the next check
    /// is planned; `None` for a run without keep mode.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keep: Option<KeepReport>,
}

/// What an iteration of a keep-mode run was ([`IterationRecord::keep`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum KeepPhase {
    /// Tuning to the targets for the first time (or after a target change).
    Tuning,
    /// A check while keeping: some parameters measured, no move.
    Check,
    /// Re-tuning after a check found a parameter out of its band.
    Retune,
}

/// Keep mode's state after an iteration: the phase, the planned next check
/// and the model's present out-of-band probabilities.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeepReport {
    /// What this iteration was.
    pub phase: KeepPhase,
    /// Lab clock time of the next planned check, s since the run's start
    /// (`None` while tuning or re-tuning).
    pub next_check_lab_seconds: Option<f64>,
    /// The parameters the next check measures.
    #[serde(default)]
    pub next_check: Vec<String>,
    /// Lab time spent out of band so far in the present re-tune, s (0 when in band).
    #[serde(default)]
    pub out_of_band_lab_seconds: f64,
}

impl IterationRecord {
    /// The record without its scans: what viewers receive by default.
    ///
    /// ```
    /// # use spintune::protocol::IterationRecord;
    /// # fn f(r: &IterationRecord) {
    /// let s = r.summary();
    /// assert!(s.scans.is_empty());
    /// assert_eq!(s.iteration, r.iteration);
    /// # }
    /// ```
    pub fn summary(&self) -> IterationRecord {
        IterationRecord {
            scans: Vec::new(),
            ..self.clone()
        }
    }
}

/// A notable event inside the tuner, attributed to the level it happened in.
///
/// ```
/// use spintune::protocol::{EventKind, TunerEvent};
/// let e = TunerEvent { level: "qubit".into(), kind: EventKind::StepLimited { from_mv: 14.2, to_mv: 10.0 } };
/// assert_eq!(e.to_string(), "qubit: step limited from 14.20 mV to 10.00 mV");
/// let json = serde_json::to_string(&e).unwrap();
/// assert!(json.contains(r#""event":"step_limited""#));
/// assert_eq!(serde_json::from_str::<TunerEvent>(&json).unwrap(), e);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TunerEvent {
    /// Name of the tuner level (e.g. `"qubit"`, `"chemical_potential"`).
    pub level: String,
    /// What happened.
    #[serde(flatten)]
    pub kind: EventKind,
}

impl std::fmt::Display for TunerEvent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.level, self.kind)
    }
}

/// The kinds of [`TunerEvent`]. Values are in the parameter's unit (`unit`)
/// or mV as named.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum EventKind {
    /// A measured value cannot be represented in the parameter's transform
    /// (e.g. ≤ 0 for a log-transformed parameter); not used.
    NotRepresentable {
        /// Parameter name.
        parameter: String,
        /// The transform, e.g. `"Log"`.
        transform: String,
    },
    /// Finite differences failed for every repetition of some gate; the
    /// gradient starts unknown (0 ± 1).
    FiniteDifferenceFailed {
        /// Parameter name.
        parameter: String,
    },
    /// The estimator refused the measured initial gradient; it starts from zero.
    InitialGradientRejected {
        /// Why.
        reason: String,
    },
    /// A value whose error bar is wider than its tolerance band is not acted on.
    TooUncertain {
        /// Parameter name.
        parameter: String,
        /// Measured value (`unit`).
        value: f64,
        /// Its standard deviation (`unit`).
        std: f64,
        /// Unit of the parameter.
        unit: String,
    },
    /// The filter's outlier gate refused a measurement.
    OutlierGated {
        /// Parameter name.
        parameter: String,
        /// Innovation `z − H g` (`unit`, estimator space).
        innovation: f64,
        /// Its predicted standard deviation (`unit`).
        innovation_sigma: f64,
        /// Unit of the parameter.
        unit: String,
    },
    /// The Newton step was scaled down to the step limit.
    StepLimited {
        /// Norm of the unlimited step, mV.
        from_mv: f64,
        /// Norm after limiting, mV.
        to_mv: f64,
    },
    /// No valid measurement of this parameter in this iteration.
    NoMeasurement {
        /// Parameter name.
        parameter: String,
    },
    /// The estimator refused an update (e.g. a non-finite innovation).
    UpdateRejected {
        /// Parameter name.
        parameter: String,
        /// Why.
        reason: String,
    },
    /// A scan could not be evaluated (fit failed, or the device reported a failure).
    EvaluationFailed {
        /// Which scan.
        scan: ScanKind,
        /// Why.
        reason: String,
    },
    /// A target of the schedule was refused.
    ScheduledTargetNotApplied {
        /// Why.
        reason: String,
    },
    /// The tuner's own check refused a planned move (nothing was sent).
    MoveRefused {
        /// Why.
        reason: String,
    },
    /// A lower level ended its call after a correction without the
    /// confirming scan: the filter predicted this parameter inside its band
    /// with margin (`NewtonConfig::skip_confirmation_sigma`).
    ConfirmationSkipped {
        /// Parameter name.
        parameter: String,
        /// Predicted value after the correction (`unit`).
        predicted: f64,
        /// Its predicted standard deviation (`unit`).
        std: f64,
        /// Unit of the parameter.
        unit: String,
    },
    /// A child level corrected from its learned forecast of a parameter
    /// instead of scanning it (`NewtonConfig::forecast`).
    MeasurementSkipped {
        /// Parameter name.
        parameter: String,
        /// Forecast value before the correction (`unit`).
        predicted: f64,
        /// Its predicted standard deviation (`unit`).
        std: f64,
        /// Unit of the parameter.
        unit: String,
    },
    /// The sensing-dot level parked its gate on the flank its learned model
    /// predicted, without a sweep (`SensingDotConfig::prediction`).
    SweepSkipped {
        /// The swept gate.
        gate: String,
        /// Predicted flank, mV of that gate.
        predicted_mv: f64,
        /// Its predicted standard deviation, mV.
        std_mv: f64,
    },
    /// The instrument's read-back differed from where the run expected the
    /// gate; the tuner continues from the read-back.
    InstrumentMoved {
        /// Gate name.
        gate: String,
        /// Where the run expected it, mV.
        expected_mv: f64,
        /// Where the instrument reads, mV.
        read_mv: f64,
    },
    /// Keep mode measured a parameter to check that it is still in its band.
    KeepCheck {
        /// Parameter name.
        parameter: String,
        /// Measured value (`unit`); `None` if the scan gave none.
        value: Option<f64>,
        /// Whether the value is inside the band.
        in_band: bool,
        /// The drift model's probability of being out of band just before
        /// the check (what scheduled it).
        predicted_out_of_band: f64,
        /// Unit of the parameter.
        unit: String,
    },
    /// An array cell that had just entered its band near the edge had this
    /// parameter scanned again where it was before the run stopped
    /// (`ArrayRunSettings::confirm_entry_sigma`): the run stops only when
    /// every such scan is in band too.
    BandEntryRechecked {
        /// Parameter name.
        parameter: String,
        /// Measured value (`unit`); `None` if the scan gave none.
        value: Option<f64>,
        /// Its standard deviation (`unit`).
        std: Option<f64>,
        /// Whether the value is inside the band (with an error bar that fits
        /// it); under `ArrayRunSettings::pool_confirmations`, whether this
        /// value and the iteration's reading, pooled by their inverse
        /// variances, are.
        in_band: bool,
        /// Unit of the parameter.
        unit: String,
    },
    /// Keep mode starts re-tuning: a check found a parameter out of band.
    RetuneStarted {
        /// Why (which parameter, its value and band).
        reason: String,
    },
    /// Keep mode is back in band after a re-tune.
    BackInBand {
        /// Lab time from the failed check to back in band, s.
        after_lab_seconds: f64,
    },
    /// Keep mode has not got back into band within the configured lab time
    /// (`KeepConfig::alert_after_s`): an alert for a person. Raised once per
    /// re-tune.
    NotBackInBand {
        /// Lab time out of band so far, s.
        out_of_band_lab_seconds: f64,
        /// The configured limit, s.
        limit_lab_seconds: f64,
    },
    /// A child level moved its gates to re-find parameters its scans lost
    /// (`NewtonConfig::search`): probe `probe` shifts each searched
    /// parameter by its offset from where the search started.
    SearchProbe {
        /// Probe number (1, 2, …).
        probe: u32,
        /// The parameters searched for.
        parameters: Vec<String>,
        /// Their intended shifts, in their estimator units (mV for lines).
        offsets: Vec<f64>,
    },
    /// A search ended: `found` after `probes` probes (the level's next
    /// step brings the parameters home), or given up (the gates went back
    /// to where the search started; no new search until a scan works).
    SearchEnded {
        /// Probes made.
        probes: u32,
        /// Whether every targeted parameter was found.
        found: bool,
    },
}

impl std::fmt::Display for EventKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            EventKind::ConfirmationSkipped {
                parameter,
                predicted,
                std,
                unit,
            } => write!(
                f,
                "{parameter}: confirming scan skipped, predicted {predicted:.3} ± {std:.3} {unit} (inside its band)"
            ),
            EventKind::MeasurementSkipped {
                parameter,
                predicted,
                std,
                unit,
            } => write!(
                f,
                "{parameter}: scan skipped, forecast {predicted:.3} ± {std:.3} {unit} (corrected without measuring)"
            ),
            EventKind::SweepSkipped {
                gate,
                predicted_mv,
                std_mv,
            } => write!(
                f,
                "sensing dot: sweep skipped, {gate} parked on the predicted flank {predicted_mv:.2} ± {std_mv:.2} mV"
            ),
            EventKind::NotRepresentable {
                parameter,
                transform,
            } => write!(f, "{parameter}: value not representable in {transform} space"),
            EventKind::FiniteDifferenceFailed { parameter } => write!(
                f,
                "{parameter}: finite differences failed for every repetition of some gate; gradient unknown (0 ± 1)"
            ),
            EventKind::InitialGradientRejected { reason } => {
                write!(f, "initial gradient rejected: {reason}")
            }
            EventKind::TooUncertain {
                parameter,
                value,
                std,
                unit,
            } => write!(
                f,
                "{parameter}: {value:.3} ± {std:.3} {unit} is too uncertain to act on"
            ),
            EventKind::OutlierGated {
                parameter,
                innovation,
                innovation_sigma,
                unit,
            } => write!(
                f,
                "{parameter}: outlier gated (innovation {innovation:.3} {unit} vs predicted σ {innovation_sigma:.3})"
            ),
            EventKind::StepLimited { from_mv, to_mv } => {
                write!(f, "step limited from {from_mv:.2} mV to {to_mv:.2} mV")
            }
            EventKind::NoMeasurement { parameter } => {
                write!(f, "{parameter}: no valid measurement this iteration")
            }
            EventKind::UpdateRejected { parameter, reason } => {
                write!(f, "{parameter}: update rejected: {reason}")
            }
            EventKind::EvaluationFailed { scan, reason } => {
                write!(f, "{scan:?} evaluation failed: {reason}")
            }
            EventKind::ScheduledTargetNotApplied { reason } => {
                write!(f, "scheduled target not applied: {reason}")
            }
            EventKind::MoveRefused { reason } => write!(f, "move refused: {reason}"),
            EventKind::InstrumentMoved {
                gate,
                expected_mv,
                read_mv,
            } => write!(
                f,
                "gate {gate} reads {read_mv:.3} mV, the run expected {expected_mv:.3} mV; continuing from the read-back"
            ),
            EventKind::KeepCheck {
                parameter,
                value,
                in_band,
                predicted_out_of_band,
                unit,
            } => {
                let verdict = if *in_band { "in band" } else { "OUT of band" };
                match value {
                    Some(v) => write!(f, "check {parameter}: {v:.3} {unit}, {verdict}")?,
                    None => write!(f, "check {parameter}: no value")?,
                }
                write!(
                    f,
                    " (predicted P(out) {:.1} %)",
                    100.0 * predicted_out_of_band
                )
            }
            EventKind::BandEntryRechecked {
                parameter,
                value,
                std,
                in_band,
                unit,
            } => {
                let verdict = if *in_band {
                    "in band: entry confirmed"
                } else {
                    "OUT of band: not yet in"
                };
                match (value, std) {
                    (Some(v), Some(s)) => write!(
                        f,
                        "{parameter} entered near its band's edge; scanned again: {v:.3} ± {s:.3} {unit}, {verdict}"
                    ),
                    _ => write!(
                        f,
                        "{parameter} entered near its band's edge; scanned again: no value, {verdict}"
                    ),
                }
            }
            EventKind::RetuneStarted { reason } => write!(f, "re-tuning: {reason}"),
            EventKind::BackInBand { after_lab_seconds } => write!(
                f,
                "back in band after {:.1} lab min",
                after_lab_seconds / 60.0
            ),
            EventKind::NotBackInBand {
                out_of_band_lab_seconds,
                limit_lab_seconds,
            } => write!(
                f,
                "ALERT: not back in band after {:.1} lab min (limit {:.1} min)",
                out_of_band_lab_seconds / 60.0,
                limit_lab_seconds / 60.0
            ),
            EventKind::SearchProbe {
                probe,
                parameters,
                offsets,
            } => {
                write!(f, "lost, search probe {probe}:")?;
                for (p, o) in parameters.iter().zip(offsets) {
                    write!(f, " {p} {o:+.2}")?;
                }
                Ok(())
            }
            EventKind::SearchEnded { probes, found } => {
                if *found {
                    write!(f, "found again after {probes} search probe(s)")
                } else {
                    write!(
                        f,
                        "not found after {probes} search probe(s): gates moved back"
                    )
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------
// Server ⇄ viewer/controller messages (REST bodies and WebSocket frames).
// ---------------------------------------------------------------------------

/// Lifecycle of a run: the modes of [`crate::session::RunSession`] plus
/// what only a server knows (`Interrupted`, `Failed`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum RunStatus {
    /// Iterating.
    Running,
    /// Running one more iteration, then `Paused`.
    Stepping,
    /// Waiting for resume or single step.
    Paused,
    /// Stop acknowledged; no further request is issued, the answer to the one
    /// already at the device is still recorded.
    Stopping,
    /// Paused by a fault (device error, lying read-back, refused request); the
    /// request is kept and re-issued on resume, after the instrument is read back.
    Faulted {
        /// What went wrong.
        fault: Fault,
    },
    /// The tuner reached its goal or its iteration limit.
    Finished,
    /// Stopped by a user. Final.
    Stopped,
    /// The server went away while the run was active; can be resumed.
    Interrupted,
    /// The run cannot continue (store failure, unreadable checkpoint, invalid
    /// config); resume retries from the last stored checkpoint.
    Failed {
        /// What went wrong.
        message: String,
    },
}

impl RunStatus {
    /// Short name, as in the JSON `state` tag.
    ///
    /// ```
    /// use spintune::protocol::{Fault, FaultKind, RunStatus};
    /// let f = RunStatus::Faulted { fault: Fault::new(FaultKind::Device, "timeout") };
    /// assert_eq!(f.name(), "faulted");
    /// assert!(f.is_resumable() && !RunStatus::Stopped.is_resumable());
    /// ```
    pub fn name(&self) -> &'static str {
        match self {
            RunStatus::Running => "running",
            RunStatus::Stepping => "stepping",
            RunStatus::Paused => "paused",
            RunStatus::Stopping => "stopping",
            RunStatus::Faulted { .. } => "faulted",
            RunStatus::Finished => "finished",
            RunStatus::Stopped => "stopped",
            RunStatus::Interrupted => "interrupted",
            RunStatus::Failed { .. } => "failed",
        }
    }

    /// Whether `resume`/`step` may continue the run from here.
    pub fn is_resumable(&self) -> bool {
        matches!(
            self,
            RunStatus::Paused
                | RunStatus::Faulted { .. }
                | RunStatus::Interrupted
                | RunStatus::Failed { .. }
        )
    }

    /// Whether the run is over for good (`finished` or `stopped`).
    pub fn is_terminal(&self) -> bool {
        matches!(self, RunStatus::Finished | RunStatus::Stopped)
    }
}

/// Why a run was paused by a fault. What clears it depends on its kind
/// ([`FaultKind::cleared_by`], the fault policy): only a
/// [`FaultKind::Disconnected`] fault clears when the device reconnects; every
/// other kind waits for a person. Whatever clears it, the instrument is read
/// back first and the kept request is checked again.
///
/// ```
/// use spintune::protocol::{ClearedBy, Fault, FaultKind};
/// let f = Fault::new(FaultKind::Device, "leakage on SB");
/// assert_eq!(f.cleared_by, ClearedBy::Resume);
/// assert_eq!(
///     serde_json::to_string(&f).unwrap(),
///     r#"{"kind":"device","message":"leakage on SB","cleared_by":"resume"}"#
/// );
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fault {
    /// Which check failed.
    pub kind: FaultKind,
    /// What happened, for a person.
    pub message: String,
    /// What clears the fault (always `kind.cleared_by()`; stated so that
    /// clients need not know the policy). Faults stored before this field
    /// read as [`ClearedBy::Resume`].
    #[serde(default = "ClearedBy::human")]
    pub cleared_by: ClearedBy,
    /// For [`FaultKind::Moved`]: every gate that reads far from where the run
    /// left it, with both positions (what `accept_positions` adopts).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub moved: Vec<MovedGate>,
}

impl Fault {
    /// A fault of `kind` (its `cleared_by` from the policy, no moved gates).
    pub fn new(kind: FaultKind, message: impl Into<String>) -> Self {
        Self {
            kind,
            message: message.into(),
            cleared_by: kind.cleared_by(),
            moved: Vec::new(),
        }
    }
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} fault: {}", self.kind.name(), self.message)
    }
}

/// A gate that reads far from where the run left it ([`FaultKind::Moved`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MovedGate {
    /// Gate name.
    pub gate: String,
    /// Where the run left it, mV: the last accepted read-back, or the range
    /// it may have been left anywhere in (a sweep, an interrupted move).
    pub left_from_mv: f64,
    /// Upper end of that range, mV (equal to `left_from_mv` for a point).
    pub left_to_mv: f64,
    /// What the instrument reads now, mV.
    pub read_mv: f64,
}

/// What clears a fault (the fault policy, [`FaultKind::cleared_by`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClearedBy {
    /// The device reconnecting (or a person's `resume`).
    Reconnect,
    /// Only a person's `resume` (after looking at the instrument).
    Resume,
    /// Only a person's `accept_positions` (confirming the gates' new
    /// positions), or `resume` after putting the gates back.
    AcceptPositions,
}

impl ClearedBy {
    /// The conservative default for faults stored before the policy.
    pub fn human() -> Self {
        ClearedBy::Resume
    }

    /// Short name, as in JSON.
    pub fn name(self) -> &'static str {
        match self {
            ClearedBy::Reconnect => "reconnect",
            ClearedBy::Resume => "resume",
            ClearedBy::AcceptPositions => "accept_positions",
        }
    }
}

/// The kinds of [`Fault`]. Every kind but [`FaultKind::Disconnected`] waits
/// for a person.
///
/// | kind | what happened | cleared by |
/// |---|---|---|
/// | `disconnected` | the device could not be reached | reconnect or resume |
/// | `device` | the instrument reported an error (e.g. leakage) | resume |
/// | `readback` | a read-back is missing, extra, not finite, outside the limits or off the set value | resume |
/// | `moved` | a gate reads far from where the run left it | accept_positions (or resume after moving it back) |
/// | `safety` | a request was refused before it reached the device | resume |
/// | `response` | the answer does not fit the request | resume |
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// The device could not be reached: the lab bridge is not connected,
    /// disconnected or did not answer in time.
    Disconnected,
    /// The device (or its driver) reported an error: leakage, a read-back
    /// mismatch inside the driver, a failed command.
    Device,
    /// A read-back was refused: gates not requested, gates missing, non-finite
    /// values, values outside the gate's limits, or a mismatch with the set
    /// value beyond the tolerance.
    Readback,
    /// A gate reads farther than `session.moved_tolerance_mv` from where the
    /// run left it (on start after a restore, resume or reconnect).
    Moved,
    /// The safety check refused a request before it reached the device
    /// (limits, step from the last read-back, sweep points).
    Safety,
    /// The answer does not fit the request (wrong kind of response).
    Response,
}

impl FaultKind {
    /// Short name, as in JSON.
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::Disconnected => "disconnected",
            FaultKind::Device => "device",
            FaultKind::Readback => "read-back",
            FaultKind::Moved => "moved",
            FaultKind::Safety => "safety",
            FaultKind::Response => "response",
        }
    }

    /// The fault policy: what clears a fault of this kind.
    ///
    /// ```
    /// use spintune::protocol::{ClearedBy, FaultKind};
    /// assert_eq!(FaultKind::Disconnected.cleared_by(), ClearedBy::Reconnect);
    /// assert_eq!(FaultKind::Device.cleared_by(), ClearedBy::Resume);
    /// assert_eq!(FaultKind::Moved.cleared_by(), ClearedBy::AcceptPositions);
    /// ```
    pub fn cleared_by(self) -> ClearedBy {
        match self {
            FaultKind::Disconnected => ClearedBy::Reconnect,
            FaultKind::Moved => ClearedBy::AcceptPositions,
            FaultKind::Device | FaultKind::Readback | FaultKind::Safety | FaultKind::Response => {
                ClearedBy::Resume
            }
        }
    }
}

/// A run as listed by the server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// Server-assigned id.
    pub id: u64,
    /// Human-readable name from the config.
    pub name: String,
    /// Current state.
    pub status: RunStatus,
    /// Number of committed iterations.
    pub iterations: u64,
    /// Cumulative lab time, s.
    pub lab_seconds: f64,
    /// Whether the last iteration was tuned.
    pub tuned: bool,
    /// The run's device driver as configured (`"simulator"`, `"scpi"` or
    /// `"bridge"`); `None` when the server does not say (servers before this
    /// field, a quarantined run).
    #[serde(default)]
    pub driver: Option<String>,
}

/// A control action. Needs the control token.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "action", rename_all = "snake_case", deny_unknown_fields)]
pub enum ControlCommand {
    /// Pause after the current request completes.
    Pause,
    /// Continue iterating.
    Resume,
    /// Run exactly one more iteration, then pause.
    Step,
    /// Stop for good.
    Stop,
    /// Confirm the positions a [`FaultKind::Moved`] fault reported (a person
    /// moved the gates, or checked that the instrument is right): the run
    /// continues from them after the next `resume`, which reads every gate
    /// again. Refused for any other status.
    AcceptPositions,
    /// Change a parameter's target and/or tolerance between iterations.
    SetTarget {
        /// Parameter name, e.g. `"t_sr"`.
        parameter: String,
        /// New target (parameter units); `null` removes the target.
        target: Option<f64>,
        /// New tolerance; omitted keeps the present one.
        #[serde(default)]
        tolerance: Option<crate::parameter::Tolerance>,
    },
}

impl ControlCommand {
    /// The command's form, whatever run it is for: a target is finite and a
    /// tolerance valid. Whether the run has the parameter and the target fits
    /// it ([`crate::parameter::ParameterSpec::check_target`]) is the run
    /// session's check; whether the run's status accepts the command is the
    /// lifecycle table ([`RunStatus::accepts`]).
    ///
    /// ```
    /// use spintune::parameter::Tolerance;
    /// use spintune::protocol::ControlCommand;
    /// let c = ControlCommand::SetTarget { parameter: "w".into(), target: Some(270.0), tolerance: Some(Tolerance::Relative(-1.0)) };
    /// assert!(c.check_form().unwrap_err().to_string().contains("tolerance"));
    /// ```
    pub fn check_form(&self) -> Result<(), ProtocolError> {
        if let ControlCommand::SetTarget {
            parameter,
            target,
            tolerance,
        } = self
        {
            if let Some(t) = target {
                if !t.is_finite() {
                    return Err(ProtocolError::NotFinite {
                        field: format!("target of {parameter:?}"),
                        value: *t,
                    });
                }
            }
            if let Some(tol) = tolerance {
                tol.validate()
                    .map_err(|error| ProtocolError::InvalidTolerance {
                        parameter: parameter.clone(),
                        error,
                    })?;
            }
        }
        Ok(())
    }
}

/// Why a run needs a person's attention ([`Alert::kind`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlertKind {
    /// The run was paused by a fault ([`RunStatus::Faulted`]).
    Faulted,
    /// The run finished ([`RunStatus::Finished`]).
    Finished,
    /// The run cannot continue ([`RunStatus::Failed`]).
    Failed,
    /// Keep mode has not got back into band within its configured lab time
    /// ([`EventKind::NotBackInBand`]).
    NotBackInBand,
}

impl AlertKind {
    /// Short name, as in JSON (`"not_back_in_band"`).
    pub fn name(self) -> &'static str {
        match self {
            AlertKind::Faulted => "faulted",
            AlertKind::Finished => "finished",
            AlertKind::Failed => "failed",
            AlertKind::NotBackInBand => "not_back_in_band",
        }
    }

    /// In plain words, for a person (`"not back in band"`).
    pub fn label(self) -> &'static str {
        match self {
            AlertKind::Faulted => "fault",
            AlertKind::Finished => "finished",
            AlertKind::Failed => "failed",
            AlertKind::NotBackInBand => "not back in band",
        }
    }
}

/// A run needs a person: it faulted, finished, failed, or keep mode has not
/// got back into band in time. Raised by [`crate::alert`] (the one place
/// that decides), sent to viewers ([`ServerMessage::Alert`]) and to the
/// server's webhook.
///
/// ```
/// use spintune::protocol::{Alert, AlertKind};
/// let a = Alert { run: 3, name: "night".into(), kind: AlertKind::NotBackInBand,
///     message: "qubit: not back in band".into(), lab_seconds: 1234.5, iteration: Some(41) };
/// let json = serde_json::to_string(&a).unwrap();
/// assert!(json.contains(r#""kind":"not_back_in_band""#));
/// assert_eq!(serde_json::from_str::<Alert>(&json).unwrap(), a);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Alert {
    /// The run's id.
    pub run: u64,
    /// The run's name.
    pub name: String,
    /// Why.
    pub kind: AlertKind,
    /// What happened, in plain words with units.
    pub message: String,
    /// The run's cumulative lab time when it happened, s.
    pub lab_seconds: f64,
    /// The iteration it happened at (the record that carried the event, or
    /// the run's last committed iteration); `None` before the first.
    #[serde(default)]
    pub iteration: Option<u64>,
}

/// Records in a [`ServerMessage::History`] page when the client names no
/// `limit` (and the page the server sends unasked after `Hello`). At about
/// 2 kB per summary record this keeps a page near 400 kB.
pub const DEFAULT_HISTORY_PAGE: u32 = 200;

/// The largest `limit` a [`ClientMessage::History`] may ask for (larger is
/// refused with an `Error` naming the bound; the socket stays open).
pub const MAX_HISTORY_PAGE: u32 = 2000;

/// Messages from a browser (or script) to the server over a run's WebSocket.
///
/// Viewers get iteration *summaries* (records with `scans` empty); the raw
/// scans and fits of one iteration are sent on request (`scans`), or with
/// every live frame after `subscribe` with `scans: true`.
///
/// ```
/// use spintune::protocol::ClientMessage;
/// let m: ClientMessage = serde_json::from_str(r#"{"type":"history","before":1200,"limit":500}"#).unwrap();
/// assert_eq!(m, ClientMessage::History { before: Some(1200), limit: Some(500) });
/// let m: ClientMessage = serde_json::from_str(r#"{"type":"history"}"#).unwrap();
/// assert_eq!(m, ClientMessage::History { before: None, limit: None });
/// let m: ClientMessage = serde_json::from_str(r#"{"type":"scans","iteration":7}"#).unwrap();
/// assert_eq!(m, ClientMessage::Scans { iteration: 7 });
/// let m: ClientMessage = serde_json::from_str(r#"{"type":"subscribe","scans":true}"#).unwrap();
/// assert_eq!(m, ClientMessage::Subscribe { scans: true, alerts: false });
/// let m: ClientMessage = serde_json::from_str(r#"{"type":"subscribe","scans":true,"alerts":true}"#).unwrap();
/// assert_eq!(m, ClientMessage::Subscribe { scans: true, alerts: true });
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ClientMessage {
    /// Present the control token; the server answers `AuthOk` or `Error`.
    Auth {
        /// The token printed by `spintune serve`.
        token: String,
    },
    /// A control action (requires a prior successful `Auth` on this socket).
    Control {
        /// What to do.
        command: ControlCommand,
    },
    /// Ask for a page of stored iteration summaries; answered by
    /// [`ServerMessage::History`]. No token needed.
    History {
        /// Only iterations numbered below this one; `None`: the newest.
        #[serde(default)]
        before: Option<u64>,
        /// Page size, default [`DEFAULT_HISTORY_PAGE`], at most
        /// [`MAX_HISTORY_PAGE`].
        #[serde(default)]
        limit: Option<u32>,
    },
    /// Ask for the scans (raw data and fits) of one stored iteration;
    /// answered by [`ServerMessage::Scans`] (or `Error` if there is no such
    /// iteration). No token needed.
    Scans {
        /// The iteration number ([`IterationRecord::iteration`]).
        iteration: u64,
    },
    /// Choose what live `Iteration` frames carry on this socket: with
    /// `scans: true` each carries its scans (the full record), otherwise a
    /// summary (the default); with `alerts: true` the socket is also sent
    /// the run's [`ServerMessage::Alert`]s (a client that does not ask
    /// never gets one). No token needed.
    Subscribe {
        /// Include raw scans and fits in live frames.
        scans: bool,
        /// Send the run's alerts on this socket (default `false`; added
        /// within protocol version 3, see [`PROTOCOL_VERSION`]).
        #[serde(default)]
        alerts: bool,
    },
}

/// Messages from the server over a run's WebSocket.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    /// First frame on every socket.
    Hello {
        /// [`PROTOCOL_VERSION`].
        version: u32,
        /// The run.
        run: RunSummary,
    },
    /// A page of stored iteration summaries (`scans` empty), oldest first,
    /// contiguous in iteration number. Sent unasked after `Hello` (the
    /// newest [`DEFAULT_HISTORY_PAGE`] iterations) and after `Lagged` (the
    /// newest page again: the client asks for older pages to fill any gap),
    /// and as the answer to [`ClientMessage::History`].
    History {
        /// Records, at most the page size.
        records: Vec<IterationRecord>,
        /// Stored iterations older than the first record of this page exist
        /// (or, for an empty page, older than `before`).
        #[serde(default)]
        more_before: bool,
    },
    /// The scans of one iteration, answering [`ClientMessage::Scans`].
    Scans {
        /// The iteration number.
        iteration: u64,
        /// Its scans with their fits (as [`IterationRecord::scans`]).
        scans: Vec<ScanReport>,
    },
    /// One new iteration, live.
    Iteration {
        /// Record.
        record: IterationRecord,
    },
    /// The run's status changed.
    Status {
        /// The run.
        run: RunSummary,
    },
    /// The viewer fell behind; the server dropped `skipped` live frames for
    /// it and follows with the newest `History` page.
    Lagged {
        /// Number of live messages dropped for this viewer.
        skipped: u64,
    },
    /// The run raised an alert ([`crate::alert`] decides when): sent live,
    /// only to sockets that subscribed with `alerts: true`; never replayed.
    Alert {
        /// What happened.
        alert: Alert,
        /// When the server raised it, RFC 3339 UTC (e.g.
        /// `2026-11-24T09:10:11Z`): wall-clock time, unlike `lab_seconds`.
        at: String,
    },
    /// Control token accepted on this socket.
    AuthOk,
    /// A request was refused or malformed; the socket stays open.
    Error {
        /// What was wrong.
        message: String,
    },
}

// ---------------------------------------------------------------------------
// Lab bridge: an external measurement script serving as a run's device, over
// the WebSocket `/api/runs/{id}/bridge` (added with protocol version 1; the
// messages above are unchanged).
// ---------------------------------------------------------------------------

/// Messages from a lab bridge client (e.g. a QCoDeS script) to the server.
///
/// The first frame must be `Auth` with the control token; afterwards the
/// client answers every [`BridgeServerMessage::Request`] with exactly one
/// `Response` carrying the request's `id`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum BridgeClientMessage {
    /// Present the control token (the same one `spintune serve` prints).
    Auth {
        /// The control token.
        token: String,
    },
    /// The answer to request `id`: `voltages_set` for `set_voltages` (the
    /// voltages actually applied, read back, mV), `scanned` for `measure`
    /// (raw traces or evaluated values ± variance), or `error`.
    Response {
        /// The id of the request being answered.
        id: u64,
        /// The answer.
        response: Response,
    },
}

/// Messages from the server to a lab bridge client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum BridgeServerMessage {
    /// First frame on every bridge socket.
    Hello {
        /// [`PROTOCOL_VERSION`].
        version: u32,
        /// The run the bridge serves.
        run: RunSummary,
    },
    /// The token was accepted; requests follow.
    AuthOk,
    /// Execute this request and answer with [`BridgeClientMessage::Response`]
    /// carrying the same `id` within `timeout_s` seconds.
    Request {
        /// Request id (unique per server process and run, increasing).
        id: u64,
        /// What to do: `set_voltages` (absolute voltages, mV, already
        /// checked against the safety limits) or `measure`.
        request: Request,
        /// Wall-clock time allowed for the answer, s; later answers are refused.
        timeout_s: f64,
    },
    /// A frame was refused or the bridge is not (or no longer) accepted; the
    /// text says why.
    Error {
        /// What was wrong.
        message: String,
    },
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parameter::Tolerance;

    /// The batch on the bridge's wire as `docs/instruments.md` shows it:
    /// the documented frames parse, and the request serializes to exactly
    /// the documented text.
    #[test]
    fn the_documented_batch_frames_are_the_wire_format() {
        let doc = include_str!("../../docs/instruments.md");
        let frame = |start: &str| {
            doc.lines()
                .find(|l| l.starts_with(start))
                .unwrap_or_else(|| panic!("no line starting {start} in docs/instruments.md"))
        };
        let request = frame(r#"{"type":"request","id":6,"#);
        let response = frame(r#"{"type":"response","id":6,"#);
        let BridgeServerMessage::Request {
            id, request: req, ..
        } = serde_json::from_str(request).unwrap()
        else {
            panic!("a request frame")
        };
        assert_eq!(id, 6);
        let Request::Batch { requests } = &req else {
            panic!("a batch")
        };
        let cells: Vec<Option<u32>> = requests
            .iter()
            .map(|r| match r {
                Request::Measure { scan } => scan.cell,
                _ => None,
            })
            .collect();
        assert_eq!(cells, [Some(0), Some(1)]);
        let sent = serde_json::to_string(&req).unwrap();
        assert!(request.contains(&sent), "{sent}\n{request}");
        let BridgeClientMessage::Response { response, .. } =
            serde_json::from_str(response).unwrap()
        else {
            panic!("a response frame")
        };
        let Response::Batch {
            responses,
            lab_seconds,
        } = response
        else {
            panic!("a batch answer")
        };
        assert_eq!(responses.len(), 2);
        assert_eq!(lab_seconds, 5.0);
    }

    #[test]
    fn run_summary_driver_round_trips_and_an_old_server_without_it_still_parses() {
        let s = RunSummary {
            id: 3,
            name: "night".into(),
            status: RunStatus::Finished,
            iterations: 12,
            lab_seconds: 40.5,
            tuned: true,
            driver: Some("scpi".into()),
        };
        let json = serde_json::to_value(&s).unwrap();
        assert_eq!(json["driver"], "scpi");
        assert_eq!(serde_json::from_value::<RunSummary>(json).unwrap(), s);
        // A summary from a server before the field: no driver, not an error.
        let old = r#"{"id":3,"name":"night","status":{"state":"finished"},"iterations":12,"lab_seconds":40.5,"tuned":true}"#;
        let parsed: RunSummary = serde_json::from_str(old).unwrap();
        assert_eq!(parsed.driver, None);
        assert_eq!(parsed.iterations, 12);
    }

    #[test]
    fn malformed_names_the_path_unless_top_level() {
        assert_eq!(
            ProtocolError::malformed(".", "expected value at line 1 column 1").to_string(),
            "malformed message: expected value at line 1 column 1"
        );
        assert_eq!(
            ProtocolError::malformed("", "x"),
            ProtocolError::Malformed {
                field: None,
                message: "x".into()
            }
        );
        assert_eq!(
            ProtocolError::malformed("command", "unknown variant `fly`").to_string(),
            "malformed message at `command`: unknown variant `fly`"
        );
        assert_eq!(
            ProtocolError::UnknownField {
                field: "command.extra".into()
            }
            .to_string(),
            "malformed message: unknown field `command.extra`"
        );
    }

    #[test]
    fn invalid_values_name_field_and_value() {
        let v = |value, variance| ParameterValue {
            name: "t_sr".into(),
            value,
            variance,
        };
        assert_eq!(v(20.0, 0.0).validate(), Ok(()));
        assert_eq!(
            v(f64::NAN, 1.0).validate().unwrap_err().to_string(),
            "value of \"t_sr\" must be a finite number, got NaN"
        );
        assert_eq!(
            v(20.0, f64::INFINITY).validate(),
            Err(ProtocolError::InvalidVariance {
                field: "variance of \"t_sr\"".into(),
                value: f64::INFINITY
            })
        );
        let error = Tolerance::Absolute(-3.0).validate().unwrap_err();
        let e = ProtocolError::InvalidTolerance {
            parameter: "w".into(),
            error,
        };
        assert_eq!(
            e.to_string(),
            "tolerance of \"w\": `absolute` must be finite and non-negative, got -3"
        );
    }
}
