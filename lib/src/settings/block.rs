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
use crate::settings::primitives::{self as read, triple};
use crate::settings::schema::{self, BlockSchema, Form, Kind, Setting};

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
    /// The settings of one block of `program`, of a kind the schema ([`crate::settings::schema`]) knows; relative
    /// input files are looked up next to the script, outputs go to `out_dir` when given and are recorded
    /// in `outputs` (shared by the run's blocks).
    pub fn new(
        program: &'p Program,
        settings: Settings,
        script_dir: &Path,
        out_dir: Option<&Path>,
        outputs: Rc<Outputs>,
    ) -> Result<Block<'p>> {
        let schema = schema::of(&settings).map_err(|d| at(program, d))?;
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

    /// The schema's setting `key`; the block must take it.
    fn setting(&self, key: &str) -> &'static Setting {
        self.schema.setting(key).unwrap_or_else(|| {
            panic!(
                "'{key}' is missing from the schema of '{}' blocks",
                self.schema.title()
            )
        })
    }

    /// Takes setting `key`, if given; `key` must be one of the schema's settings of the block.
    pub fn take(&mut self, key: &str) -> Option<Spanned> {
        self.setting(key);
        self.settings.take(key)
    }

    /// Takes setting `key`, if given, checked against its form in the schema (a value with a grammar of its
    /// own by the schema's check, where it has one).
    pub fn value(&mut self, key: &str) -> Result<Option<Spanned>> {
        let setting = self.setting(key);
        let Some(v) = self.settings.take(key) else {
            return Ok(None);
        };
        schema::validate(setting, &v).map_err(|d| self.error(d))?;
        Ok(Some(v))
    }

    /// Takes setting `key`, which must be given (the schema says how).
    pub fn required(&mut self, key: &str) -> Result<Spanned> {
        let setting = self.setting(key);
        self.take(key)
            .ok_or_else(|| self.error(schema::missing(self.schema, setting, self.span())))
    }

    /// Number setting `key`, or its default.
    pub fn number(&mut self, key: &str) -> Result<f64> {
        let Form::Number { default, .. } = self.setting(key).form else {
            panic!("'{key}' is not a number in the schema")
        };
        match self.value(key)? {
            Some(v) => v.number().map_err(|d| self.error(d)),
            None => Ok(default),
        }
    }

    /// Whole-number setting `key`, or its default, if it has one.
    pub fn whole_or_none(&mut self, key: &str) -> Result<Option<u64>> {
        let Form::Whole { default, .. } = self.setting(key).form else {
            panic!("'{key}' is not a whole number in the schema")
        };
        match self.value(key)? {
            Some(v) => v.number().map(|x| Some(x as u64)).map_err(|d| self.error(d)),
            None => Ok(default),
        }
    }

    /// Whole-number setting `key`, or its default.
    pub fn whole(&mut self, key: &str) -> Result<u64> {
        Ok(self
            .whole_or_none(key)?
            .unwrap_or_else(|| panic!("'{key}' has no default in the schema")))
    }

    /// The interval of settings `near` and `far` as read, far beyond near.
    pub fn interval(&self, near: f64, far: f64) -> Result<(f32, f32)> {
        let (near, far) = (near as f32, far as f32);
        if far <= near {
            return Err(self.block_error(format!("far ({far}) must exceed near ({near})")));
        }
        Ok((near, far))
    }

    /// The `spacing` setting `v` as read (linear when absent), checked against [near, far].
    pub fn spacing_of(
        &self,
        v: Option<&Spanned>,
        near: f32,
        far: f32,
    ) -> Result<nerfjit_runtime::DepthSpacing> {
        let Some(v) = v else {
            return Ok(nerfjit_runtime::DepthSpacing::Linear);
        };
        let spacing = crate::settings::values::depth_spacing(v).map_err(|d| self.error(d))?;
        spacing.check(near, far).map_err(|e| {
            self.error(Diagnostic::new(v.span, e.to_string()).with_hint("raise near above 0 or the split"))
        })?;
        Ok(spacing)
    }

    /// Three-number setting `key`, or its default, if it has one.
    pub fn triple(&mut self, key: &str) -> Result<Option<[f32; 3]>> {
        let Form::Triple { default } = self.setting(key).form else {
            panic!("'{key}' is not three numbers in the schema")
        };
        match self.value(key)? {
            Some(v) => triple(&v).map(Some).map_err(|d| self.error(d)),
            None => Ok(default),
        }
    }

    /// Setting `key`, one of the bare names the schema lists, or its default, if it has one.
    pub fn choice(&mut self, key: &str) -> Result<Option<String>> {
        let Form::Choice { choices, default } = self.setting(key).form else {
            panic!("'{key}' is not a choice in the schema")
        };
        match self.take(key) {
            Some(v) => read::name_among(&v, choices).map(Some).map_err(|d| self.error(d)),
            None => Ok(default.map(str::to_string)),
        }
    }

    /// Setting `key`, `true` or `false`, or its default.
    pub fn flag(&mut self, key: &str) -> Result<bool> {
        Ok(self.choice(key)?.as_deref() == Some("true"))
    }

    /// Setting `key`, the name of a function (a string), or its default.
    pub fn function(&mut self, key: &str) -> Result<String> {
        let Form::Function { default } = self.setting(key).form else {
            panic!("'{key}' is not a function name in the schema")
        };
        let Some(v) = self.value(key)? else {
            return Ok(default.to_string());
        };
        let name = v.string().map_err(|d| self.error(d))?;
        if self.program.signature(name).is_none() {
            let mut d = self.program.no_function(name, v.span);
            d.message = format!("setting '{key}': {}", d.message);
            return Err(self.error(d));
        }
        Ok(name.to_string())
    }

    /// The cameras a camera value describes (at least one).
    pub fn cameras_of(&self, v: &Spanned) -> Result<Vec<Camera>> {
        let made = crate::settings::camera::cameras(v, &self.script_dir).map_err(|d| self.error(d))?;
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

    /// Size setting `key`: `N` or `[width, height]`, or its default.
    pub fn size(&mut self, key: &str) -> Result<(u32, u32)> {
        let Form::Size { default } = self.setting(key).form else {
            panic!("'{key}' is not a size in the schema")
        };
        match self.value(key)? {
            Some(v) => read::size(&v, schema::MAX_SIDE).map_err(|d| self.error(d)),
            None => Ok((default, default)),
        }
    }

    /// Output setting `key`: the file it names (with an extension the schema allows), or, when absent and
    /// the schema writes it by default, `<script>.<suffix>` (the script's file stem, then `-2`, `-3`, … if
    /// an earlier block took that name) in the working folder or in `--out`; `None` for no file.
    pub fn output(&mut self, key: &str) -> Result<Option<PathBuf>> {
        let Form::Output { formats, by_default } = self.setting(key).form else {
            panic!("'{key}' is not an output in the schema")
        };
        if let Some(v) = self.take(key) {
            return match read::output_name(&v, formats, by_default.is_some()) {
                Ok(Some(written)) => self.resolve_output(&v, written).map(Some),
                Ok(None) => Ok(None),
                Err(d) => Err(self.error(d)),
            };
        }
        let Some(suffix) = by_default else {
            return Ok(None);
        };
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

    /// Output setting `key`, which must be given.
    pub fn required_output(&mut self, key: &str) -> Result<PathBuf> {
        if self.settings.span_of(key).is_none() {
            self.required(key)?;
        }
        Ok(self.output(key)?.expect("given"))
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

    /// Fails on the first setting not taken, suggesting the closest the block takes.
    pub fn finish(self) -> Result<()> {
        self.settings
            .finish(&self.schema.names())
            .map_err(|d| at(self.program, d))
    }
}
