//! The terminal side of a run: progress bars (indicatif) and Ctrl-C (ctrlc).

use indicatif::ProgressStyle;
use nerfjit::interrupt;
use nerfjit::observe::{BarKind, ProgressBar, ProgressBars};

/// Progress bars drawn on the terminal (hidden when standard error is not one).
pub struct TerminalBars;

struct Bar(indicatif::ProgressBar);

impl ProgressBars for TerminalBars {
    fn bar(&self, len: u64, kind: BarKind) -> Box<dyn ProgressBar> {
        let template = match kind {
            BarKind::Steps(verb) => {
                format!("{{spinner}} {verb} [{{bar:30}}] {{pos}}/{{len}} {{msg}} {{elapsed}}, {{eta}} to go")
            }
            BarKind::Frames(what) => {
                format!("{{spinner}} {what} [{{bar:30}}] {{pos}}/{{len}} frames {{elapsed}}")
            }
        };
        Box::new(Bar(indicatif::ProgressBar::new(len).with_style(
            ProgressStyle::with_template(&template).unwrap_or_else(|_| ProgressStyle::default_bar()),
        )))
    }
}

impl ProgressBar for Bar {
    fn set_position(&self, position: u64) {
        self.0.set_position(position);
    }

    fn set_message(&self, message: String) {
        self.0.set_message(message);
    }

    fn println(&self, line: String) {
        if self.0.is_hidden() {
            eprintln!("{line}");
        } else {
            self.0.println(line);
        }
    }

    fn finish_and_clear(&self) {
        self.0.finish_and_clear();
    }

    fn abandon(&self) {
        self.0.abandon();
    }
}

/// Installs the Ctrl-C and SIGTERM handler (once, at start): see [`nerfjit::interrupt`].
pub fn install_interrupt_handler() {
    if let Err(e) = ctrlc::set_handler(interrupt::on_signal) {
        eprintln!("warning: Ctrl-C will not save a checkpoint: {e}");
    }
}
