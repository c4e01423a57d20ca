//! SIGINT (Ctrl-C) and SIGTERM (a cluster's time limit) during training.
//!
//! The first signal sets [`StopControl`]'s flag: the step in progress finishes, burn writes a
//! complete checkpoint ([`super::stop`]) and `train` exits with `128 + signal` after saying
//! how to resume. A second signal of either kind exits at once with that code (what was
//! written stays valid: a half-written checkpoint is skipped by `--resume`).
//!
//! Handlers are registered through `signal-hook` (async-signal-safe: they only store atomics
//! or call `_exit`) and unregistered when [`SignalGuard`] drops, so a library caller that
//! trains several times does not pile up handlers. Only Unix has these signals; elsewhere
//! [`SignalGuard::install`] installs nothing.

use super::stop::StopControl;
use crate::error::Result;
use crate::error::exit_code;

/// The signals that stop a run: SIGINT (2) and SIGTERM (15).
#[cfg(unix)]
pub const STOP_SIGNALS: [i32; 2] = [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM];

/// The name of a signal number, for messages.
pub fn name(signal: usize) -> String {
    match signal {
        2 => "SIGINT".into(),
        15 => "SIGTERM".into(),
        s => format!("signal {s}"),
    }
}

/// Registered handlers; dropping the guard unregisters them.
#[derive(Debug)]
pub struct SignalGuard {
    #[cfg(unix)]
    ids: Vec<signal_hook::SigId>,
}

impl SignalGuard {
    /// Routes SIGINT and SIGTERM to `stop` (first signal) and to an immediate exit (second).
    #[cfg(unix)]
    pub fn install(stop: &StopControl) -> Result<Self> {
        use signal_hook::flag;
        use std::sync::{Arc, atomic::AtomicBool};
        let fail =
            |e: std::io::Error| crate::error::Error::invalid("signals", "register", e.to_string());
        let seen = Arc::new(AtomicBool::new(false));
        let mut ids = Vec::new();
        for sig in STOP_SIGNALS {
            // Order matters: handlers run in registration order, so the exit sees the flag
            // the first signal set only from the second signal on.
            ids.push(
                flag::register_conditional_shutdown(
                    sig,
                    exit_code(sig as usize) as i32,
                    seen.clone(),
                )
                .map_err(fail)?,
            );
            ids.push(flag::register(sig, seen.clone()).map_err(fail)?);
            ids.push(flag::register_usize(sig, stop.signal_flag(), sig as usize).map_err(fail)?);
        }
        Ok(SignalGuard { ids })
    }

    /// No signals to handle on this platform.
    #[cfg(not(unix))]
    pub fn install(_stop: &StopControl) -> Result<Self> {
        Ok(SignalGuard {})
    }
}

impl Drop for SignalGuard {
    fn drop(&mut self) {
        #[cfg(unix)]
        for id in self.ids.drain(..) {
            signal_hook::low_level::unregister(id);
        }
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    #[test]
    fn names_and_exit_codes_follow_the_shell() {
        assert_eq!(name(2), "SIGINT");
        assert_eq!(name(15), "SIGTERM");
        assert_eq!(exit_code(2), 130);
        assert_eq!(exit_code(15), 143);
    }

    #[test]
    fn a_raised_signal_sets_the_flag_and_the_guard_unregisters() {
        let stop = StopControl::new();
        let guard = SignalGuard::install(&stop).unwrap();
        // SIGTERM to this process: the first one only sets the flag.
        signal_hook::low_level::raise(signal_hook::consts::SIGTERM).unwrap();
        assert_eq!(stop.signal(), Some(15));
        drop(guard);
    }
}
