//! Progress on stderr while a command reads an event file: a bar of bytes
//! read against the file size, the events decoded, their rate and an ETA.
//!
//! The library reports a reading pass's progress through callbacks
//! (`ReadRate`, `ReadBar` turn them into a bar). Drawing is
//! limited to `REFRESH_HZ` and happens only when stderr is a terminal
//! (indicatif hides the bar otherwise: pipes, logs and tests stay quiet).

use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// Redraws per second at most.
pub(crate) const REFRESH_HZ: u8 = 10;

/// Bar layout after `simulate`'s (`{msg} [{bar:40}] … ({eta})`); the
/// message last, cut to the terminal's width.
const BAR_TEMPLATE: &str = "{prefix} [{bar:20}] {bytes}/{total_bytes} ({eta}) {wide_msg}";
/// Size unknown (standard input): no bar and no ETA.
const SPINNER_TEMPLATE: &str = "{spinner} {prefix} {bytes} {wide_msg}";

/// The style of `simulate`'s bar: `=` done, `>` the head, blank to do.
pub(crate) fn style(template: &str) -> ProgressStyle {
    ProgressStyle::with_template(template)
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ")
}

/// A bar for reading `total` bytes (a spinner when the size is unknown),
/// drawn on stderr at most [`REFRESH_HZ`] times a second.
pub(crate) fn file_bar(total: Option<u64>, what: &str) -> ProgressBar {
    let target = ProgressDrawTarget::stderr_with_hz(REFRESH_HZ);
    let bar = ProgressBar::with_draw_target(total, target);
    bar.set_style(style(if total.is_some() {
        BAR_TEMPLATE
    } else {
        SPINNER_TEMPLATE
    }));
    bar.set_prefix(what.to_string());
    bar
}

/// `1234567` → `1.23 M`, `12` → `12 `.
pub(crate) fn count(n: f64) -> String {
    if n >= 1e9 {
        format!("{:.2} G", n / 1e9)
    } else if n >= 1e6 {
        format!("{:.1} M", n / 1e6)
    } else if n >= 1e3 {
        format!("{:.1} k", n / 1e3)
    } else {
        format!("{n:.0} ")
    }
}

/// The event rate of a reading pass, for the bar's message.
#[derive(Default)]
pub(crate) struct ReadRate {
    started: Option<Instant>,
    shown: Option<Instant>,
}

impl ReadRate {
    /// Moves the bar at most [`REFRESH_HZ`] times a second
    /// (and on the last chunk).
    pub(crate) fn show(
        &mut self,
        bar: &ProgressBar,
        bytes: u64,
        events: u64,
        done: bool,
        note: Option<String>,
    ) {
        let now = Instant::now();
        let started = *self.started.get_or_insert(now);
        let due = self.shown.is_none_or(|t| {
            now.duration_since(t) >= Duration::from_millis(1000 / REFRESH_HZ as u64)
        });
        if !(due || done) {
            return;
        }
        self.shown = Some(now);
        bar.set_position(bytes);
        let secs = now.duration_since(started).as_secs_f64();
        let rate = if secs > 0.0 {
            events as f64 / secs
        } else {
            0.0
        };
        let mut msg = format!("{}ev, {}ev/s", count(events as f64), count(rate));
        if let Some(note) = note {
            msg.push_str(", ");
            msg.push_str(&note);
        }
        bar.set_message(msg);
    }
}

/// The bar of a command whose library call reads one file and reports
/// `Opened` then `Read` progress (`pulses`, `info`).
pub(crate) struct ReadBar {
    what: &'static str,
    bar: Option<ProgressBar>,
    rate: ReadRate,
}

impl ReadBar {
    /// No bar until the file is open; `what` is its prefix.
    pub(crate) fn new(what: &'static str) -> Self {
        ReadBar {
            what,
            bar: None,
            rate: ReadRate::default(),
        }
    }

    /// The file is open: a bar sized from `file_size` (a spinner without).
    pub(crate) fn opened(&mut self, file_size: Option<u64>) {
        self.bar = Some(file_bar(file_size, self.what));
    }

    /// After a chunk: bytes read and events decoded so far; the bar is
    /// cleared on the last chunk.
    pub(crate) fn read(&mut self, bytes: u64, events: u64, done: bool) {
        if let Some(b) = self.bar.as_ref().filter(|b| !b.is_hidden()) {
            self.rate.show(b, bytes, events, done, None);
        }
        if done {
            if let Some(b) = self.bar.take() {
                b.finish_and_clear();
            }
        }
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn counts_are_short() {
        assert_eq!(count(0.0), "0 ");
        assert_eq!(count(999.0), "999 ");
        assert_eq!(count(12_345.0), "12.3 k");
        assert_eq!(count(22_530_000.0), "22.5 M");
        assert_eq!(count(3.2e9), "3.20 G");
    }
}
