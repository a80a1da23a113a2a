//! `bake { ... }`: the script's volume field, with the params as they are at that point, baked into Gaussian
//! splats as `nerfjit bake` bakes a checkpoint. This module reads and checks the block's settings; the baking
//! itself is [`crate::commands::bake`]'s, above the session, which reaches it through the
//! [`crate::session::Baker`] its caller gives.

use std::path::PathBuf;

use nerfjit_dsl::Diagnostic;

use crate::failure::{at, Result};
use crate::settings::block::Block;
use crate::settings::schema::Kind;
use crate::settings::typed::typed_settings;

typed_settings! {
    /// The settings of a `bake` block, as read.
    pub struct BakeSettings for crate::settings::schema::BAKE {
        out: required_output,
        tune: number,
        sh_degree: whole,
        min_weight: number,
        size: whole_or_none,
        min_opacity: number,
    }
}

/// A checked `bake` block: what `nerfjit bake` takes as options.
#[derive(Debug, Clone, PartialEq)]
pub struct BakePlan {
    /// The `.bake` file to write.
    pub out: PathBuf,
    /// Seconds of fine-tuning (0: none).
    pub tune_seconds: f64,
    /// The degree of the tuned splats' spherical harmonics (0 or 1).
    pub sh_degree: u8,
    /// Halfway through tuning, splats that weighed under this many pixels (of a view as wide as those
    /// baked) in every view are dropped (but for those near the edges of every frame that holds them).
    pub min_weight: f32,
    /// The larger side of the views rendered to bake, in pixels (in the training views' shape; by default half
    /// their larger side).
    pub size: Option<u32>,
    /// Pixels of the views below this opacity are left out.
    pub min_opacity: f32,
}

impl BakePlan {
    /// Reads and checks a `bake` block. The script must have a `train { }` block: its data's views are
    /// those the field is baked from and tuned against.
    pub fn new(mut b: Block) -> Result<BakePlan> {
        let s = BakeSettings::read(&mut b)?;
        let (program, span) = (b.program(), b.span());
        b.finish()?;
        let trains = program
            .blocks()
            .into_iter()
            .any(|block| crate::settings::schema::kind_of(block) == Some(Kind::Train));
        if !trains {
            let message =
                "a bake block bakes the field from the views of the script's train block's data, and \
                           this script has no train block";
            let hint = "add a 'train { data: ... }' block before it";
            return Err(at(program, Diagnostic::new(span, message).with_hint(hint)));
        }
        Ok(BakePlan {
            out: s.out,
            tune_seconds: s.tune,
            sh_degree: s.sh_degree as u8,
            min_weight: s.min_weight as f32,
            size: s.size.map(|s| s as u32),
            min_opacity: s.min_opacity as f32,
        })
    }
}
