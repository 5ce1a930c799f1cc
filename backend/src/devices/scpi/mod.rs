//! SCPI driver for a multi-channel DC voltage source over raw TCP
//! (QDAC-II style; one command per line, `\n`-terminated).
//!
//! The subset used (`scpi.profile`, [`ScpiProfile`]):
//!
//! | command | profile | meaning |
//! |---|---|---|
//! | `sour{ch}:volt:mode fix` | qdac2 | on connect: fixed DC mode (a channel left in list/sweep mode does not follow `sour{ch}:volt`) |
//! | `sour{ch}:volt:slew {V/s}` | both | the instrument's own ramp rate, V/s (no answer) |
//! | `sour{ch}:volt?` | generic | read channel `ch` back; answers one line, volts |
//! | `sour{ch}:volt:last?` | qdac2 | the present output of `ch`, volts (`volt?` may echo the set point) |
//! | `sour{ch}:volt {V}` | both | set channel `ch` to `V` volts (no answer) |
//! | `read{ch}?` | qdac2 with `max_leakage_na` or `max_leakage_na_by_gate` | after every move, for every moved channel: the current it sources, A (comma-separated list; the largest magnitude counts) |
//!
//! The tuner works in mV, the instrument in V: every value is divided by
//! 1000 on the way out (formatted with 6 decimals, i.e. 1 µV resolution) and
//! multiplied by 1000 on the way back.
//!
//! Safety, on top of the run session's guard (which checks every request
//! against the limits and the instrument's last read-back as the session
//! accepted it), enforced against the *driver's own* read-back state before
//! any command is sent:
//!
//! 1. every gate must be mapped to a channel and have a [`GateSpec`];
//! 2. the target must lie within the gate's `[min_mv, max_mv]`;
//! 3. the change from the voltage last read back from the instrument must not
//!    exceed the gate's `max_step_mv`;
//! 4. the move is split into equal increments no larger than
//!    [`ScpiConfig::ramp_step_mv`] (all gates of the request advance together);
//!    every planned command is checked against the limits before the first is
//!    sent;
//! 5. after the last increment every channel is read back and compared with
//!    the target ([`ScpiConfig::readback_tolerance_mv`]); a mismatch is an
//!    error (the run pauses, nothing is retried silently).
//!
//! Numbers from the instrument are believed only if they are finite and not
//! SCPI's special values (`9.91E37` is NaN, `±9.9E37` is ±infinity/overflow,
//! [`scpi_number`](commands::scpi_number)); anything else drops the connection and faults.
//!
//! Any I/O error or timeout drops the connection and forgets the instrument
//! state. The failed request is reported as an error (the run pauses with the
//! message); nothing is re-sent by the driver. When the run is resumed the
//! tuner re-issues the request, the driver reconnects, reads every channel
//! back and ramps from wherever the instrument really is — after checking the
//! step again.
//!
//! | file | what it is |
//! |---|---|
//! | [`config`] | the `[scpi]` table ([`ScpiConfig`], [`ScpiProfile`], [`MeasureSource`]), its bounds and validation |
//! | [`commands`] | the command strings, numbers from the instrument ([`scpi_number`](commands::scpi_number)), the ramp plan ([`plan_ramp`](commands::plan_ramp)) |
//! | [`source`] | [`ScpiSource`]: the TCP client of the DC source and the checks above |
//! | [`device`] | [`ScpiDevice`]: the source for the gates plus a measuring device |

mod commands;
mod config;
mod device;
mod source;
#[cfg(test)]
mod tests;

#[cfg(test)]
use commands::{plan_ramp, query_command, scpi_number, set_command, slew_command};
pub use config::{MeasureSource, ScpiConfig, ScpiProfile};
pub use device::ScpiDevice;
pub use source::ScpiSource;
