//! Ctrl-C, `SIGTERM` and `SIGHUP`: one handler for the whole process (a process can install
//! only one). During training the first interrupt asks the trainer to stop at the end of its
//! step and write a checkpoint ([`GracefulStop`]); otherwise, or at a second interrupt, the
//! temporary files of the atomic writes in progress are removed and the process exits with
//! status 130, as a shell reports an interrupted command. Files under their final names are
//! never partial (they are renamed into place whole), so nothing else needs cleaning.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::{Context, Result};

/// The stop flag of the training in progress, if any.
static TRAINING: Mutex<Option<Arc<AtomicBool>>> = Mutex::new(None);

/// The exit status of an interrupted command (128 + SIGINT's number, as shells report it).
pub const INTERRUPTED: i32 = 130;

pub fn install() -> Result<()> {
    ctrlc::set_handler(|| {
        let training = TRAINING.lock().ok().and_then(|t| t.clone());
        if let Some(flag) = training
            && !flag.swap(true, Ordering::SeqCst)
        {
            eprintln!(
                "\ninterrupted: stopping after this step and writing a checkpoint \
                 (interrupt again to quit at once)"
            );
            return;
        }
        let removed = f3g_io::remove_pending_temporaries();
        eprintln!(
            "\ninterrupted{}",
            match removed {
                0 => String::new(),
                n => format!(": removed {n} unfinished file(s)"),
            }
        );
        std::process::exit(INTERRUPTED);
    })
    .context("installing the interrupt handler")
}

/// While it lives, an interrupt raises [`GracefulStop::flag`] instead of ending the process.
pub struct GracefulStop {
    flag: Arc<AtomicBool>,
}

impl GracefulStop {
    pub fn new() -> Self {
        let flag = Arc::new(AtomicBool::new(false));
        *TRAINING.lock().unwrap_or_else(|e| e.into_inner()) = Some(flag.clone());
        Self { flag }
    }

    /// Raised by an interrupt (or by whoever else wants the trainer to stop).
    pub fn flag(&self) -> &Arc<AtomicBool> {
        &self.flag
    }
}

impl Drop for GracefulStop {
    fn drop(&mut self) {
        *TRAINING.lock().unwrap_or_else(|e| e.into_inner()) = None;
    }
}
