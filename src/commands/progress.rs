//! Training progress: an indicatif bar on a terminal, and `tracing` lines
//! every 5% of the run otherwise (logs, CI, `nohup`), where a bar is invisible;
//! and the Ctrl-C flag long runs checkpoint on.

use std::io::IsTerminal;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use indicatif::{ProgressBar, ProgressStyle};

pub struct Progress {
    bar: ProgressBar,
    total: u64,
    terminal: bool,
    stage: &'static str,
}

impl Progress {
    pub fn new(stage: &'static str, total: u32) -> Self {
        let bar = ProgressBar::new(u64::from(total));
        bar.set_style(
            ProgressStyle::with_template("{bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {per_sec} {msg}")
                .expect("valid template"),
        );
        Self { bar, total: u64::from(total), terminal: std::io::stderr().is_terminal(), stage }
    }

    /// Report iteration `it`; `message` is only built when it will be shown.
    pub fn update(&self, it: u32, message: impl FnOnce() -> String) {
        let it = u64::from(it);
        self.bar.set_position(it);
        if self.terminal {
            if it.is_multiple_of(10) {
                self.bar.set_message(message());
            }
        } else if it.is_multiple_of((self.total / 20).max(1)) {
            tracing::info!("{} {it}/{}: {}", self.stage, self.total, message());
        }
    }

    /// Start again from 0 (the next interaction's stage).
    pub fn restart(&self) {
        self.bar.reset();
    }

    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// A flag that Ctrl-C raises. A second Ctrl-C is not caught again: the handler
/// only raises the flag, and the run checkpoints and stops when it sees it.
pub fn interrupt_on_ctrl_c() -> Arc<AtomicBool> {
    let interrupt = Arc::new(AtomicBool::new(false));
    let flag = interrupt.clone();
    let _ = ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst));
    interrupt
}
