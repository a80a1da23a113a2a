//! Typed access to the settings of one block, with errors pointing into the script. Every setting is
//! taken once; [`Block::finish`] rejects any left over as unknown.

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use nerfjit_dsl::ast::ConfigBlock;
use nerfjit_dsl::config::{Settings, Spanned, Value};
use nerfjit_dsl::{Diagnostic, Program, Span};
use nerfjit_runtime::Camera;

use crate::failure::{at, Failure, Result};
use crate::schema::{self, BlockSchema, Kind};
use crate::settings::{name_among, ranged, triple, whole};

/// The most pixels a render block may produce (all frames).
pub const MAX_PIXELS: u64 = 1 << 27;

/// The files a script's blocks write so far, with the settings that name them: no two outputs of a run
/// may be the same file (one would silently replace the other, e.g. a summary its checkpoint).
#[derive(Default)]
pub struct Outputs(RefCell<Vec<(PathBuf, Span)>>);

/// A block's settings with what resolving them needs.
pub struct Block<'p> {
    program: &'p Program,
    schema: &'static BlockSchema,
    settings: Settings,
    script_dir: PathBuf,
    out_dir: Option<PathBuf>,
    outputs: Rc<Outputs>,
}

/// The first block of `kind` in `program` (a script in `script_dir`), read with its outputs redirected to
/// the OS temp folder: for commands that use a block's settings without running it. (`Kind::Train` finds
/// a `train { }` block, never a `train sdf { }` one.)
pub fn first_block<'p>(program: &'p Program, kind: Kind, script_dir: &str) -> Result<Block<'p>> {
    let is_kind = |b: &&ConfigBlock| schema::kind_of(b) == Some(kind);
    let block = program.blocks().into_iter().find(is_kind).ok_or_else(|| {
        Failure::Message(format!(
            "the script has no '{}' block",
            schema::of_kind(kind).title()
        ))
    })?;
    let settings = Settings::new(program, block).map_err(|d| at(program, d))?;
    let temp = std::env::temp_dir();
    Block::new(
        program,
        settings,
        Path::new(script_dir),
        Some(&temp),
        Rc::default(),
    )
}

impl<'p> Block<'p> {
    /// The settings of one block of `program`, of a kind the [schema](crate::schema) knows; relative
    /// input files are looked up next to the script, outputs go to `out_dir` when given and are recorded
    /// in `outputs` (shared by the run's blocks).
    pub fn new(
        program: &'p Program,
        settings: Settings,
        script_dir: &Path,
        out_dir: Option<&Path>,
        outputs: Rc<Outputs>,
    ) -> Result<Block<'p>> {
        let schema = crate::schema::of(&settings).map_err(|d| at(program, d))?;
        Ok(Block {
            program,
            schema,
            settings,
            script_dir: script_dir.to_path_buf(),
            out_dir: out_dir.map(Path::to_path_buf),
            outputs,
        })
    }

    /// The kind of block and the settings it takes.
    pub fn schema(&self) -> &'static BlockSchema {
        self.schema
    }

    /// The program the block belongs to.
    pub fn program(&self) -> &'p Program {
        self.program
    }

    /// The folder of the script.
    pub fn script_dir(&self) -> &Path {
        &self.script_dir
    }

    /// An error at `span` of the script.
    pub fn error(&self, d: Diagnostic) -> Failure {
        at(self.program, d)
    }

    /// An error about the whole block.
    pub fn block_error(&self, message: String) -> Failure {
        self.error(Diagnostic::new(self.settings.span, message))
    }

    /// The whole block's span.
    pub fn span(&self) -> Span {
        self.settings.span
    }

    /// Takes setting `key`, if given; `key` must be one of the schema's settings of the block.
    pub fn take(&mut self, key: &str) -> Option<Spanned> {
        assert!(
            self.schema.settings.contains(&key),
            "'{key}' is missing from the schema of '{}' blocks",
            self.schema.title()
        );
        self.settings.take(key)
    }

    /// Takes setting `key`, which must be given (`example` shows how).
    pub fn required(&mut self, key: &str, example: &str) -> Result<Spanned> {
        let kind = self.settings.kind.clone();
        self.take(key).ok_or_else(|| {
            self.error(
                Diagnostic::new(self.span(), format!("the {kind} block needs '{key}'"))
                    .with_hint(format!("add e.g. {example}")),
            )
        })
    }

    /// Setting `key` as a number in `lo..=hi`, or `default`.
    pub fn number(&mut self, key: &str, lo: f64, hi: f64, default: f64) -> Result<f64> {
        match self.take(key) {
            Some(v) => ranged(&v, lo, hi).map_err(|d| self.error(d)),
            None => Ok(default),
        }
    }

    /// Setting `key` as a whole number in `lo..=hi`, or `default`.
    pub fn whole(&mut self, key: &str, lo: u64, hi: u64, default: u64) -> Result<u64> {
        match self.take(key) {
            Some(v) => whole(&v, lo, hi).map_err(|d| self.error(d)),
            None => Ok(default),
        }
    }

    /// Settings `near` and `far` (defaults 0 and `default_far`), far beyond near.
    pub fn near_far(&mut self, default_far: f64) -> Result<(f32, f32)> {
        let near = self.number("near", 0.0, 1e6, 0.0)? as f32;
        let far = self.number("far", 0.0, 1e9, default_far)? as f32;
        if far <= near {
            return Err(self.block_error(format!("far ({far}) must exceed near ({near})")));
        }
        Ok((near, far))
    }

    /// The `spacing` setting for sampling [near, far] (linear by default), checked against the interval.
    pub fn spacing(&mut self, near: f32, far: f32) -> Result<nerfjit_runtime::DepthSpacing> {
        let Some(v) = self.take("spacing") else {
            return Ok(nerfjit_runtime::DepthSpacing::Linear);
        };
        let spacing = crate::volume::depth_spacing(&v).map_err(|d| self.error(d))?;
        spacing.check(near, far).map_err(|e| {
            self.error(Diagnostic::new(v.span, e.to_string()).with_hint("raise near above 0 or the split"))
        })?;
        Ok(spacing)
    }

    /// Setting `key` as three numbers (one number is repeated), if given.
    pub fn triple(&mut self, key: &str) -> Result<Option<[f32; 3]>> {
        self.take(key)
            .map(|v| triple(&v))
            .transpose()
            .map_err(|d| self.error(d))
    }

    /// Setting `key` as one of the bare names `choices`, or `default`.
    pub fn choice(&mut self, key: &str, choices: &[&str], default: &str) -> Result<String> {
        match self.take(key) {
            Some(v) => name_among(&v, choices).map_err(|d| self.error(d)),
            None => Ok(default.to_string()),
        }
    }

    /// Setting `camera`: the cameras of a path or a file.
    pub fn cameras(&mut self) -> Result<Vec<Camera>> {
        let v = self.required(
            "camera",
            "camera: surround(radius: 3, frames: 20, up: z, focal: 1)",
        )?;
        self.cameras_of(&v)
    }

    /// The cameras a camera value describes (at least one).
    pub fn cameras_of(&self, v: &Spanned) -> Result<Vec<Camera>> {
        let made = crate::cameras::cameras(v, &self.script_dir).map_err(|d| self.error(d))?;
        let cameras = made.map_err(|e| self.error(Diagnostic::new(v.span, e)))?;
        if cameras.is_empty() {
            return Err(self.error(Diagnostic::new(v.span, "these settings give no camera")));
        }
        Ok(cameras)
    }

    /// Checks that `frames` images of `size` fit in memory (all frames are kept for the GIF).
    pub fn check_pixels(&self, frames: usize, size: (u32, u32)) -> Result<()> {
        let pixels = frames as u64 * u64::from(size.0) * u64::from(size.1);
        if pixels > MAX_PIXELS {
            return Err(self.block_error(format!(
                "{frames} frames of {}×{} are {pixels} pixels, more than the {MAX_PIXELS} kept in memory at once",
                size.0, size.1
            )));
        }
        Ok(())
    }

    /// Setting `size`: `N` or `[width, height]`, 1 to 8192; 256 when absent.
    pub fn size(&mut self) -> Result<(u32, u32)> {
        let Some(v) = self.take("size") else {
            return Ok((256, 256));
        };
        let side = |x: &Spanned| whole(x, 1, 8192).map(|n| n as u32).map_err(|d| self.error(d));
        match &v.value {
            Value::List(items) if items.len() == 2 => Ok((side(&items[0])?, side(&items[1])?)),
            _ => side(&v).map(|n| (n, n)),
        }
    }

    /// Setting `key` as an output file, if given: its folder must exist; `--out` replaces the folder.
    pub fn output(&mut self, key: &str) -> Result<Option<PathBuf>> {
        let Some(v) = self.take(key) else {
            return Ok(None);
        };
        let written = PathBuf::from(v.string().map_err(|d| self.error(d))?);
        self.resolve_output(&v, written).map(Some)
    }

    /// Setting `key` as an output file that is written by default: `none` turns it off; when absent it is
    /// `<script>.<suffix>` (the script's file stem, then `-2`, `-3`, … if an earlier block took that name)
    /// in the working folder or in `--out`.
    pub fn default_output(&mut self, key: &str, suffix: &str) -> Result<Option<PathBuf>> {
        match self.take(key) {
            Some(v) if matches!(&v.value, Value::Name(n) if n == "none") => Ok(None),
            Some(v) => {
                let written = PathBuf::from(v.string().map_err(|d| self.error(d))?);
                self.resolve_output(&v, written).map(Some)
            }
            None => {
                let script = Path::new(&self.program.sources.files[1].name);
                let stem = script.file_stem().unwrap_or_default().to_string_lossy();
                let taken = |path: &Path| self.outputs.0.borrow().iter().any(|(p, _)| p == path);
                let path = (1..)
                    .map(|k| {
                        let numbered = if k == 1 { String::new() } else { format!("-{k}") };
                        let name = format!("{stem}{numbered}.{suffix}");
                        match &self.out_dir {
                            Some(dir) => dir.join(name),
                            None => PathBuf::from(name),
                        }
                    })
                    .find(|p| !taken(p))
                    .expect("unbounded");
                let v = Spanned {
                    value: Value::Str(path.display().to_string()),
                    span: self.span(),
                };
                self.resolve_output(&v, path).map(Some)
            }
        }
    }

    /// Where output `written` (from setting `v`) goes: into `--out` when given; its folder must exist.
    pub fn resolve_output(&self, v: &Spanned, written: PathBuf) -> Result<PathBuf> {
        let path = match &self.out_dir {
            Some(dir) => dir.join(written.file_name().unwrap_or_default()),
            None => written,
        };
        let folder = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        if !folder.is_dir() {
            return Err(self.error(
                Diagnostic::new(
                    v.span,
                    format!(
                        "cannot write '{}': folder '{}' does not exist",
                        path.display(),
                        folder.display()
                    ),
                )
                .with_hint("create the folder first, or pass --out DIR"),
            ));
        }
        let mut outputs = self.outputs.0.borrow_mut();
        if let Some((_, earlier)) = outputs.iter().find(|(p, _)| *p == path) {
            let (line, col) = self.position(*earlier);
            return Err(self.error(
                Diagnostic::new(
                    v.span,
                    format!(
                        "'{}' is written twice: also by the setting at line {line}, column {col}",
                        path.display()
                    ),
                )
                .with_hint("give each output its own file name (--out keeps only the names)"),
            ));
        }
        outputs.push((path.clone(), v.span));
        Ok(path)
    }

    /// The line and column (from 1) of `span`'s start in its file.
    fn position(&self, span: Span) -> (usize, usize) {
        let at = span.start as usize;
        match self.program.sources.file_at(at) {
            Some(file) => nerfjit_dsl::diag::line_col(&file.text, at - file.base),
            None => (0, 0),
        }
    }

    /// Setting `key` as an image output (`.gif` or `.mp4` for all frames, `.png` for one or numbered
    /// frames).
    pub fn image_output(&mut self, key: &str) -> Result<Option<PathBuf>> {
        self.output_as(key, &["gif", "mp4", "png"])
    }

    /// Setting `key` as a depth output, if given: an image (see [`Block::image_output`]) or float depths
    /// in a NumPy `.npy` file.
    pub fn depth_output(&mut self, key: &str) -> Result<Option<PathBuf>> {
        self.output_as(key, &["gif", "mp4", "png", "npy"])
    }

    /// Setting `key` as an output file whose extension is one of `formats`.
    fn output_as(&mut self, key: &str, formats: &[&str]) -> Result<Option<PathBuf>> {
        let span = self.settings_span(key);
        let path = self.output(key)?;
        if let Some(p) = &path {
            let extension = p.extension().and_then(|e| e.to_str()).unwrap_or("");
            if !formats.contains(&extension) {
                let listed: Vec<String> = formats.iter().map(|f| format!(".{f}")).collect();
                return Err(self.error(
                    Diagnostic::new(span, format!("cannot write '{}': unknown format", p.display()))
                        .with_hint(format!("use a file ending in {}", listed.join(", "))),
                ));
            }
        }
        Ok(path)
    }

    /// Setting `key` as an image output, which must be given.
    pub fn required_image_output(&mut self, key: &str, example: &str) -> Result<PathBuf> {
        if self.settings.span_of(key).is_none() {
            self.required(key, example)?;
        }
        Ok(self.image_output(key)?.expect("present"))
    }

    fn settings_span(&self, key: &str) -> Span {
        self.settings.span_of(key).unwrap_or(self.settings.span)
    }

    /// Fails on the first setting not taken, suggesting the closest the block takes.
    pub fn finish(self) -> Result<()> {
        self.settings
            .finish(self.schema.settings)
            .map_err(|d| at(self.program, d))
    }
}
