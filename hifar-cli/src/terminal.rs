//! Keeping the terminal for hifar while training code writes to the log.
//!
//! XLA, MuJoCo and absl write warnings straight to file descriptors 1 and 2, below Python's
//! `sys.stdout`/`sys.stderr`. While a [`Capture`] lives, both descriptors point at the run's
//! log; hifar's own lines and the progress bar go to a duplicate of the original stderr
//! through [`Console`]. Dropping the capture restores the descriptors.

use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::Path;
use std::sync::{Arc, Mutex};

/// Where hifar's own messages go: the terminal's stderr, even while it is captured.
#[derive(Clone)]
pub struct Console {
    out: Arc<Mutex<File>>,
    is_term: bool,
}

impl Console {
    /// Writes one line (best effort: a closed terminal must not stop training).
    pub fn line(&self, text: &str) {
        let mut out = self.out.lock().unwrap_or_else(|p| p.into_inner());
        let _ = writeln!(out, "{text}");
    }

    pub fn is_term(&self) -> bool {
        self.is_term
    }

    /// A `console::Term` on the same descriptor, for indicatif.
    pub fn term(&self) -> io::Result<console::Term> {
        let fd = self.out.lock().unwrap_or_else(|p| p.into_inner()).as_raw_fd();
        let write = File::from(dup(fd)?);
        let read = File::from(dup(fd)?);
        Ok(console::Term::read_write_pair(read, write))
    }
}

/// Descriptors 1 and 2 redirected to a log file until dropped.
pub struct Capture {
    saved_stdout: OwnedFd,
    saved_stderr: OwnedFd,
    console: Console,
}

impl Capture {
    pub fn start(log: &Path) -> io::Result<Capture> {
        let _ = io::stdout().flush();
        let _ = io::stderr().flush();
        let log = OpenOptions::new().create(true).append(true).open(log)?;
        let saved_stdout = dup(libc::STDOUT_FILENO)?;
        let saved_stderr = dup(libc::STDERR_FILENO)?;
        let console_fd = dup(saved_stderr.as_raw_fd())?;
        dup2(log.as_raw_fd(), libc::STDOUT_FILENO)?;
        if let Err(err) = dup2(log.as_raw_fd(), libc::STDERR_FILENO) {
            let _ = dup2(saved_stdout.as_raw_fd(), libc::STDOUT_FILENO);
            return Err(err);
        }
        // SAFETY: isatty only inspects the descriptor.
        let is_term = unsafe { libc::isatty(console_fd.as_raw_fd()) } == 1;
        let console = Console { out: Arc::new(Mutex::new(File::from(console_fd))), is_term };
        Ok(Capture { saved_stdout, saved_stderr, console })
    }

    pub fn console(&self) -> Console {
        self.console.clone()
    }
}

impl Drop for Capture {
    fn drop(&mut self) {
        let _ = io::stdout().flush();
        let _ = dup2(self.saved_stdout.as_raw_fd(), libc::STDOUT_FILENO);
        let _ = dup2(self.saved_stderr.as_raw_fd(), libc::STDERR_FILENO);
    }
}

fn dup(fd: i32) -> io::Result<OwnedFd> {
    // SAFETY: dup returns a new descriptor that we own, or -1.
    let new = unsafe { libc::fcntl(fd, libc::F_DUPFD_CLOEXEC, 0) };
    if new < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: `new` is a fresh descriptor owned by nobody else.
    Ok(unsafe { OwnedFd::from_raw_fd(new) })
}

fn dup2(from: i32, to: i32) -> io::Result<()> {
    // SAFETY: dup2 on descriptors that are open for the duration of the call.
    if unsafe { libc::dup2(from, to) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// A flag raised by the first SIGINT or SIGTERM, which long commands poll to stop cleanly
/// (checkpoint, or write nothing); a second signal while the first is handled exits at once.
pub fn interrupt_flag() -> io::Result<Arc<std::sync::atomic::AtomicBool>> {
    let flag = Arc::new(std::sync::atomic::AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(signal, 130, Arc::clone(&flag))?;
        signal_hook::flag::register(signal, Arc::clone(&flag))?;
    }
    Ok(flag)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn captured_descriptors_write_to_the_log_and_are_restored() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("log.txt");
        {
            let capture = Capture::start(&log).unwrap();
            // Raw descriptor writes, as C code (XLA) would do them.
            let msg = b"from fd 2\n";
            // SAFETY: writing a valid buffer to fd 2.
            unsafe { libc::write(libc::STDERR_FILENO, msg.as_ptr().cast(), msg.len()) };
            capture.console().line("to the console");
        }
        // Descriptors are process-wide: lines other tests print while the capture lives land in
        // the log too, so only this test's own lines are checked.
        let text = std::fs::read_to_string(&log).unwrap();
        assert!(text.lines().any(|line| line == "from fd 2"), "{text:?}");
        assert!(!text.contains("to the console"), "{text:?}");
    }
}
