//! What the program says: command output on standard output, news and warnings on standard error (rank 0
//! alone in an MPI job).

use crate::cluster;

/// Writes command output to standard output; a closed pipe (`nerfjit ir ... | head`) ends the output
/// quietly instead of panicking.
pub fn emit(text: &str) {
    use std::io::Write;
    // In an MPI job, rank 0 alone prints.
    if cluster::current().rank() != 0 {
        return;
    }
    let _ = std::io::stdout().lock().write_all(text.as_bytes());
}

/// Writes a line of news or warning to standard error; in an MPI job, rank 0 alone does.
pub fn note(line: &str) {
    if cluster::current().rank() == 0 {
        eprintln!("{line}");
    }
}
