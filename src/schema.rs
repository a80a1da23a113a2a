//! The block kinds a script may hold and the settings each takes: one registry, read by the blocks
//! (which reject any setting not in it), by `nerfjit check` (which rejects unknown blocks and misspelt
//! settings without running anything), and by a test that keeps the tables of `docs/LANGUAGE.md` in step
//! with it; a block that reads a setting missing here fails loudly in every test that runs it. The
//! settings' types, ranges and defaults are still checked where each block reads them.

use nerfjit_dsl::ast::ConfigBlock;
use nerfjit_dsl::config::Settings;
use nerfjit_dsl::Diagnostic;

/// The kinds of block, one per schema.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// `render sphere_trace { }`.
    SphereTrace,
    /// `render volume { }`.
    Volume,
    /// `train { }`.
    Train,
    /// `train sdf { }`.
    TrainSdf,
    /// `mesh { }`.
    Mesh,
    /// `viz { }`.
    Viz,
}

/// A block kind and the names of its settings.
#[derive(Debug)]
pub struct BlockSchema {
    /// Which kind it is.
    pub id: Kind,
    /// The keyword that opens the block (`render`).
    pub kind: &'static str,
    /// The word after it, for kinds that have one (`sphere_trace` in `render sphere_trace { }`).
    pub variant: Option<&'static str>,
    /// The settings it takes.
    pub settings: &'static [&'static str],
}

impl BlockSchema {
    /// How the block is written: `render sphere_trace`, `train`.
    pub fn title(&self) -> String {
        match self.variant {
            Some(v) => format!("{} {v}", self.kind),
            None => self.kind.to_string(),
        }
    }
}

/// `render sphere_trace { }`.
pub const RENDER_SPHERE_TRACE: BlockSchema = BlockSchema {
    id: Kind::SphereTrace,
    kind: "render",
    variant: Some("sphere_trace"),
    settings: &[
        "camera",
        "size",
        "near",
        "far",
        "eps",
        "max_steps",
        "background",
        "shading",
        "light",
        "albedo",
        "bounds",
        "out",
        "depth",
        "normals",
        "frame_ms",
    ],
};

/// `render volume { }`.
pub const RENDER_VOLUME: BlockSchema = BlockSchema {
    id: Kind::Volume,
    kind: "render",
    variant: Some("volume"),
    settings: &[
        "camera",
        "size",
        "near",
        "far",
        "samples",
        "background",
        "early_termination",
        "spacing",
        "skip_empty",
        "importance",
        "out",
        "depth",
        "frame_ms",
    ],
};

/// `train { }`: fitting a field to images.
pub const TRAIN: BlockSchema = BlockSchema {
    id: Kind::Train,
    kind: "train",
    variant: None,
    settings: &[
        "data",
        "near",
        "far",
        "samples",
        "background",
        "steps",
        "batch",
        "lr",
        "schedule",
        "views",
        "jitter",
        "seed",
        "checkpoint",
        "checkpoint_every",
        "summary",
        "preview",
        "preview_every",
        "sdf",
        "eikonal_weight",
        "eikonal_points",
        "eikonal_bounds",
        "val",
        "val_every",
        "val_views",
        "val_minutes",
        "importance",
        "skip_empty",
        "grid_every",
        "grid_warmup",
        "grid_update",
        "minutes",
        "early_termination",
        "spacing",
        "optimizer",
        "log",
        "tensorboard",
    ],
};

/// `train sdf { }`: fitting a function to a point cloud.
pub const TRAIN_SDF: BlockSchema = BlockSchema {
    id: Kind::TrainSdf,
    kind: "train",
    variant: Some("sdf"),
    settings: &[
        "data",
        "function",
        "steps",
        "batch",
        "random",
        "bounds",
        "lr",
        "schedule",
        "optimizer",
        "near_weight",
        "near_sharpness",
        "eikonal_weight",
        "eikonal_jitter",
        "pretrain_steps",
        "pretrain_radius",
        "seed",
        "checkpoint",
        "checkpoint_every",
        "log",
        "tensorboard",
        "summary",
        "points_gif",
    ],
};

/// `mesh { }`.
pub const MESH: BlockSchema = BlockSchema {
    id: Kind::Mesh,
    kind: "mesh",
    variant: None,
    settings: &[
        "function",
        "resolution",
        "bounds",
        "level",
        "out",
        "gif",
        "compare",
    ],
};

/// `viz { }`: the course's teaching images.
pub const VIZ: BlockSchema = BlockSchema {
    id: Kind::Viz,
    kind: "viz",
    variant: None,
    settings: &[
        "camera",
        "view",
        "size",
        "near",
        "far",
        "samples",
        "rays",
        "grid",
        "directions",
        "points",
    ],
};

/// Every block kind, in the order of the language reference.
pub const BLOCKS: &[&BlockSchema] = &[
    &RENDER_SPHERE_TRACE,
    &RENDER_VOLUME,
    &TRAIN,
    &TRAIN_SDF,
    &MESH,
    &VIZ,
];

/// The schema of the block `settings` were read from, or a diagnostic at the block naming the kinds.
pub fn of(settings: &Settings) -> Result<&'static BlockSchema, Diagnostic> {
    find(&settings.kind, settings.name.as_deref()).ok_or_else(|| {
        let what = match &settings.name {
            Some(n) => format!("{} {n}", settings.kind),
            None => settings.kind.clone(),
        };
        let kinds: Vec<String> = BLOCKS.iter().map(|s| format!("'{} {{ }}'", s.title())).collect();
        Diagnostic::new(settings.span, format!("there are no '{what}' blocks"))
            .with_hint(format!("blocks are {}", kinds.join(", ")))
    })
}

/// The schema of blocks opened by `keyword` and `variant` (`render`, `Some("volume")`), if any.
pub fn find(keyword: &str, variant: Option<&str>) -> Option<&'static BlockSchema> {
    BLOCKS
        .iter()
        .copied()
        .find(|s| s.kind == keyword && s.variant == variant)
}

/// The kind of a script's block, if the schema knows it.
pub fn kind_of(block: &ConfigBlock) -> Option<Kind> {
    let variant = block.name.as_ref().map(|n| n.name.as_str());
    find(&block.kind.name, variant).map(|s| s.id)
}

/// The schema of `kind`.
pub fn of_kind(kind: Kind) -> &'static BlockSchema {
    BLOCKS
        .iter()
        .copied()
        .find(|s| s.id == kind)
        .expect("every kind has a schema")
}

/// Checks that `settings` belong to a known block kind and that each is one it takes (a misspelt one
/// gets "did you mean"); their values are checked when the block is read.
pub fn check(settings: &Settings) -> Result<(), Diagnostic> {
    let schema = of(settings)?;
    let mut rest = settings.clone();
    for key in schema.settings {
        rest.take(key);
    }
    rest.finish(schema.settings)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings_of(script: &str) -> Settings {
        let program = nerfjit_dsl::compile("s.sdf", script).unwrap();
        Settings::new(&program, program.blocks()[0]).unwrap()
    }

    #[test]
    fn blocks_are_told_apart_by_keyword_and_variant() {
        let script = "fn sdf(p: vec3) -> f32 = length(p) - 1\ntrain sdf { steps: 1 }\ntrain { steps: 1 }\n\
                      render volume { size: 8 }\nrender sphere_trace { size: 8 }\nrender ray_march { size: 8 }";
        let program = nerfjit_dsl::compile("s.sdf", script).unwrap();
        let kinds: Vec<Option<Kind>> = program.blocks().into_iter().map(kind_of).collect();
        let want = [
            Some(Kind::TrainSdf),
            Some(Kind::Train),
            Some(Kind::Volume),
            Some(Kind::SphereTrace),
            None,
        ];
        assert_eq!(kinds, want);
        for schema in BLOCKS {
            assert_eq!(of_kind(schema.id).title(), schema.title());
        }
    }

    #[test]
    fn a_misspelt_setting_is_named_with_the_closest_one() {
        let settings = settings_of("fn sdf(p: vec3) -> f32 = length(p) - 1\ntrain sdf { stesp: 10 }");
        let error = check(&settings).unwrap_err();
        assert!(
            error.message.contains("unknown setting 'stesp'"),
            "{}",
            error.message
        );
        assert_eq!(error.hint.as_deref(), Some("did you mean 'steps'?"));
    }

    #[test]
    fn an_unknown_block_kind_lists_the_kinds() {
        let settings = settings_of("fn sdf(p: vec3) -> f32 = length(p) - 1\nrender ray_march { size: 8 }");
        let error = check(&settings).unwrap_err();
        assert!(
            error.message.contains("no 'render ray_march' blocks"),
            "{}",
            error.message
        );
        assert!(error.hint.unwrap().contains("'render sphere_trace { }'"));
    }

    /// The setting names a section of the language reference documents: the first column of its table,
    /// or, for a section without one, every name in backticks.
    fn documented(reference: &str, schema: &BlockSchema) -> (Vec<String>, bool) {
        let heading = format!("### `{} {{ ... }}`", schema.title());
        let start = reference
            .find(&heading)
            .unwrap_or_else(|| panic!("no section '{heading}'"));
        let section = &reference[start + heading.len()..];
        let section = &section[..section.find("\n#").unwrap_or(section.len())];
        let rows: Vec<&str> = section.lines().filter(|l| l.starts_with("| `")).collect();
        let text: Vec<&str> = if rows.is_empty() {
            vec![section]
        } else {
            rows.iter().map(|r| r.split('|').nth(1).unwrap()).collect()
        };
        let names = text
            .iter()
            .flat_map(|t| t.split('`').skip(1).step_by(2))
            .map(|quoted| {
                quoted
                    .split(|c: char| !(c.is_alphanumeric() || c == '_'))
                    .next()
                    .unwrap()
            })
            .map(str::to_string)
            .collect();
        (names, !rows.is_empty())
    }

    #[test]
    fn the_language_reference_documents_every_setting_and_no_other() {
        let reference = include_str!("../docs/LANGUAGE.md");
        for schema in BLOCKS {
            let (names, tabled) = documented(reference, schema);
            for setting in schema.settings {
                let title = schema.title();
                assert!(
                    names.iter().any(|n| n == setting),
                    "'{title}' does not document '{setting}'"
                );
            }
            if tabled {
                for name in &names {
                    assert!(
                        schema.settings.contains(&name.as_str()),
                        "'{}' documents '{name}', which it does not take",
                        schema.title()
                    );
                }
            }
        }
    }

    #[test]
    fn known_settings_pass_whatever_their_values() {
        let settings = settings_of("fn sdf(p: vec3) -> f32 = length(p) - 1\nmesh { resolution: -3, out: 7 }");
        assert!(check(&settings).is_ok());
    }
}
