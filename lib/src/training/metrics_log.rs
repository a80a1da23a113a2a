//! A training run's metrics log: one record per line, as JSON Lines, or as CSV when the file name ends in
//! `.csv`. A fresh run replaces the file; a resumed run appends to it. Each record is written at once, so
//! the file can be followed while training runs. [`RunLog`] also sends the records to TensorBoard.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::failure::{Failure, Result};
use crate::training::tensorboard::EventWriter;

/// A line of a metrics log, named: a struct declared with `log_record!`, whose fields are the log's
/// columns (the step first), so that no caller writes a row by position.
pub trait LogRecord {
    /// The log's columns: the record's field names, in order.
    const COLUMNS: &'static [&'static str];
    /// This line's value in each column (`None`: empty on this line).
    fn values(&self) -> Vec<Option<f64>>;
}

/// A value a log record holds: a number, or an optional one (empty on lines without it).
pub trait LogValue {
    /// The value as written, if there is one.
    fn value(&self) -> Option<f64>;
}

impl LogValue for u32 {
    fn value(&self) -> Option<f64> {
        Some(f64::from(*self))
    }
}

impl LogValue for f64 {
    fn value(&self) -> Option<f64> {
        Some(*self)
    }
}

impl LogValue for Option<f32> {
    fn value(&self) -> Option<f64> {
        self.map(f64::from)
    }
}

impl LogValue for Option<f64> {
    fn value(&self) -> Option<f64> {
        *self
    }
}

/// Declares a [`LogRecord`]: a struct of public fields, each a column of the log (named as the field; the
/// step first), each a [`LogValue`].
macro_rules! log_record {
    ($(#[$meta:meta])* $vis:vis struct $name:ident { $($(#[$doc:meta])* $field:ident: $ty:ty,)* }) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, Default)]
        $vis struct $name {
            $($(#[$doc])* pub $field: $ty,)*
        }

        impl $crate::training::metrics_log::LogRecord for $name {
            const COLUMNS: &'static [&'static str] = &[$(stringify!($field)),*];

            fn values(&self) -> Vec<Option<f64>> {
                vec![$($crate::training::metrics_log::LogValue::value(&self.$field)),*]
            }
        }
    };
}
pub(crate) use log_record;

/// Where a run's records go: the metrics file and TensorBoard, each if asked for. The first column is the
/// step; TensorBoard gets every other column as a scalar of that name.
pub struct RunLog {
    file: Option<MetricsLog>,
    board: Option<EventWriter>,
    columns: &'static [&'static str],
}

impl RunLog {
    /// Opens the metrics file `file` (see [`MetricsLog::open`]) and a new event file in the TensorBoard
    /// folder `board`, each if given.
    pub fn open(
        file: Option<&Path>,
        board: Option<&Path>,
        columns: &'static [&'static str],
        append: bool,
    ) -> Result<RunLog> {
        Ok(RunLog {
            file: file.map(|f| MetricsLog::open(f, columns, append)).transpose()?,
            board: board.map(EventWriter::create).transpose()?,
            columns,
        })
    }

    /// The columns of the records.
    pub fn columns(&self) -> &'static [&'static str] {
        self.columns
    }

    /// Writes one record: a value (or nothing) per column, the step first.
    pub fn record(&mut self, values: &[Option<f64>]) -> Result<()> {
        if let Some(file) = &mut self.file {
            file.record(values)?;
        }
        if let (Some(board), Some(Some(step))) = (&mut self.board, values.first()) {
            for (tag, value) in self.columns.iter().zip(values).skip(1) {
                if let Some(x) = value {
                    board.scalar(tag, *step as u64, *x as f32)?;
                }
            }
        }
        Ok(())
    }
}

/// An open metrics log with a fixed set of columns.
pub struct MetricsLog {
    path: PathBuf,
    out: File,
    columns: &'static [&'static str],
    csv: bool,
}

impl MetricsLog {
    /// Opens `path` for records of `columns` (appending when `append` and the file exists; a new CSV
    /// file starts with its header line).
    pub fn open(path: &Path, columns: &'static [&'static str], append: bool) -> Result<MetricsLog> {
        let fail = |e: std::io::Error| Failure::Message(format!("cannot write '{}': {e}", path.display()));
        let csv = path.extension().is_some_and(|e| e == "csv");
        let continued = append && path.is_file();
        let file = OpenOptions::new()
            .create(true)
            .write(true)
            .append(continued)
            .truncate(!continued)
            .open(path)
            .map_err(fail)?;
        let mut log = MetricsLog {
            path: path.to_path_buf(),
            out: file,
            columns,
            csv,
        };
        if csv && !continued {
            writeln!(log.out, "{}", columns.join(",")).map_err(fail)?;
        }
        Ok(log)
    }

    /// Writes one record: a value (or nothing) per column.
    pub fn record(&mut self, values: &[Option<f64>]) -> Result<()> {
        let line = if self.csv {
            let cells: Vec<String> = values
                .iter()
                .map(|v| v.map_or(String::new(), |x| x.to_string()))
                .collect();
            cells.join(",")
        } else {
            let fields: serde_json::Map<String, serde_json::Value> = self
                .columns
                .iter()
                .zip(values)
                .filter_map(|(c, v)| v.map(|x| (c.to_string(), number(x))))
                .collect();
            serde_json::Value::Object(fields).to_string()
        };
        self.out
            .write_all(format!("{line}\n").as_bytes())
            .map_err(|e| Failure::Message(format!("cannot write '{}': {e}", self.path.display())))
    }
}

/// `x` as JSON: whole numbers (steps) without a fraction.
fn number(x: f64) -> serde_json::Value {
    if x.fract() == 0.0 && x.abs() < 9e15 {
        serde_json::json!(x as i64)
    } else {
        serde_json::json!(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const COLUMNS: &[&str] = &["step", "loss", "val_psnr"];

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-log-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn json_lines_hold_the_given_columns_and_a_resumed_run_appends() {
        let path = temp("m.jsonl");
        let mut log = MetricsLog::open(&path, COLUMNS, false).unwrap();
        log.record(&[Some(10.0), Some(0.5), None]).unwrap();
        drop(log);
        let mut log = MetricsLog::open(&path, COLUMNS, true).unwrap();
        log.record(&[Some(20.0), Some(0.25), Some(21.5)]).unwrap();
        drop(log);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<serde_json::Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        assert_eq!(lines.len(), 2);
        assert_eq!(lines[0], serde_json::json!({"step": 10, "loss": 0.5}));
        assert_eq!(lines[1]["val_psnr"], 21.5);
        // A fresh run starts the file again.
        drop(MetricsLog::open(&path, COLUMNS, false).unwrap());
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "");
    }

    #[test]
    fn csv_has_a_header_and_empty_cells_for_missing_values() {
        let path = temp("m.csv");
        let mut log = MetricsLog::open(&path, COLUMNS, false).unwrap();
        log.record(&[Some(10.0), Some(0.5), None]).unwrap();
        drop(log);
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "step,loss,val_psnr\n10,0.5,\n"
        );
    }
}
