//! Training progress: an indicatif bar on a terminal, and `tracing` lines
//! every 5% of the run otherwise (logs, CI, `nohup`), where a bar is invisible;
//! and the Ctrl-C flag long runs checkpoint on.

use std::io::IsTerminal;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use aim::stream::SessionEvent;
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

    /// Start again from 0 on a schedule of `total` iterations (the next interaction's stage).
    pub fn restart(&mut self, total: u32) {
        self.total = u64::from(total);
        self.bar.reset();
        self.bar.set_length(self.total);
    }

    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// A session's progress as `aim run` and `aim batch` show it: a bar per stage,
/// a line per event.
pub struct SessionProgress {
    stage_one: std::sync::Mutex<Progress>,
    stage_two: std::sync::Mutex<Progress>,
}

impl SessionProgress {
    pub fn new() -> Self {
        SessionProgress {
            stage_one: std::sync::Mutex::new(Progress::new("stage I", 0)),
            stage_two: std::sync::Mutex::new(Progress::new("stage II", 0)),
        }
    }

    pub fn on_event(&self, e: SessionEvent) {
        match e {
            SessionEvent::Window(w) => println!("motion window: {w:?}"),
            SessionEvent::StageOneStarted { interaction, object, views, iterations } => {
                lock(&self.stage_one).restart(iterations);
                println!("interaction {}: stage I starts on {views} frame(s) of object {object}", interaction + 1)
            }
            SessionEvent::StageOne(r) => {
                lock(&self.stage_one).update(r.iteration, || format!("psnr {:.2} gaussians {}", r.psnr, r.gaussians))
            }
            SessionEvent::StageTwoStarted { interaction, motion, end, iterations } => {
                lock(&self.stage_one).finish();
                lock(&self.stage_two).restart(iterations);
                println!(
                    "interaction {}: stages II and III on {motion} motion frames and {end} end-state frames",
                    interaction + 1
                );
            }
            SessionEvent::StageTwo(s) => lock(&self.stage_two).update(s.iteration, || format!("psnr {:.2}", s.psnr)),
            SessionEvent::Articulated { interaction, parts, hand_out_to_articulation_s } => {
                lock(&self.stage_two).finish();
                println!(
                    "interaction {}: {} moving part(s) and their joints{}; meshes and export follow",
                    interaction + 1,
                    parts.len(),
                    hand_out_to_articulation_s.map_or(String::new(), |s| format!(", {s:.1} s after hand-out"))
                );
            }
        }
    }

    pub fn finish(&self) {
        lock(&self.stage_one).finish();
        lock(&self.stage_two).finish();
    }
}

fn lock(p: &std::sync::Mutex<Progress>) -> std::sync::MutexGuard<'_, Progress> {
    p.lock().unwrap_or_else(|e| e.into_inner())
}

/// A flag that Ctrl-C (and SIGTERM, as engines stop a worker) raises. A second
/// Ctrl-C is not caught again: the handler only raises the flag, and the run
/// checkpoints and stops when it sees it.
pub fn interrupt_on_ctrl_c() -> Arc<AtomicBool> {
    let interrupt = Arc::new(AtomicBool::new(false));
    let flag = interrupt.clone();
    let _ = ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst));
    interrupt
}
