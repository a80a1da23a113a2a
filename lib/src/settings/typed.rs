//! Typed settings: a block's settings read once into a struct with a field per setting of its schema, so
//! that plans read fields, not names. `typed_settings!` declares the struct from the schema's names (the
//! field is named as the setting) and the reader of each setting's form; a test checks every such struct
//! against its schema, name by name and form by form, so the schema stays the one list of settings.

/// Declares a block's typed settings: `struct Name for SCHEMA { setting: reader, ... }`, one field per
/// setting of `SCHEMA` in its order, each read by the [`Block`](crate::settings::block::Block) method of
/// its form: `number` (`f64`), `whole` (`u64`), `whole_or_none` (`Option<u64>`), `flag` (`bool`), `choice`
/// (`Option<String>`), `triple` (`Option<[f32; 3]>`), `size` (`(u32, u32)`), `function` (`String`), `output`
/// (`Option<PathBuf>`), `required_output` (`PathBuf`), `required` (a value that must be given) or `value` (a
/// value with a grammar of its own, parsed by the plan with its diagnostics). Absent settings take the
/// schema's defaults.
macro_rules! typed_settings {
    ($(#[$meta:meta])* $vis:vis struct $name:ident for $schema:path { $($field:ident: $reader:ident,)* }) => {
        $(#[$meta])*
        #[derive(Debug, Clone)]
        $vis struct $name {
            $(
                #[doc = concat!("Setting `", stringify!($field), "` (read as `", stringify!($reader), "`).")]
                pub $field: typed_settings!(@type $reader),
            )*
        }

        impl $name {
            /// Reads every setting of the block, absent ones as the schema's defaults, each checked
            /// against its form.
            pub fn read(b: &mut $crate::settings::block::Block) -> $crate::failure::Result<$name> {
                Ok($name {
                    $($field: typed_settings!(@read b, $reader, stringify!($field)),)*
                })
            }
        }

        impl $crate::settings::typed::TypedSettings for $name {
            const SCHEMA: &'static $crate::settings::schema::BlockSchema = &$schema;
            const FIELDS: &'static [(&'static str, &'static str)] =
                &[$((stringify!($field), stringify!($reader))),*];
        }
    };
    (@type number) => { f64 };
    (@type whole) => { u64 };
    (@type whole_or_none) => { Option<u64> };
    (@type flag) => { bool };
    (@type choice) => { Option<String> };
    (@type triple) => { Option<[f32; 3]> };
    (@type size) => { (u32, u32) };
    (@type function) => { String };
    (@type output) => { Option<std::path::PathBuf> };
    (@type required_output) => { std::path::PathBuf };
    (@type required) => { nerfjit_dsl::config::Spanned };
    (@type value) => { Option<nerfjit_dsl::config::Spanned> };
    (@read $b:ident, value, $key:expr) => { $b.value($key)? };
    (@read $b:ident, $reader:ident, $key:expr) => { $b.$reader($key)? };
}
pub(crate) use typed_settings;

/// What a struct of `typed_settings!` says of itself, for the test against its schema.
pub trait TypedSettings {
    /// The schema of the block kind.
    const SCHEMA: &'static crate::settings::schema::BlockSchema;
    /// Each field's name and reader, in order.
    const FIELDS: &'static [(&'static str, &'static str)];
}

#[cfg(test)]
mod tests {
    use super::TypedSettings;
    use crate::settings::schema::Form;

    /// Whether `reader` reads settings of `form`.
    fn reads(reader: &str, form: &Form, required: bool) -> bool {
        match form {
            Form::Number { .. } => reader == "number",
            Form::Whole { default: Some(_), .. } => reader == "whole" || reader == "whole_or_none",
            Form::Whole { default: None, .. } => reader == "whole_or_none",
            Form::Choice { choices, .. } if *choices == ["true", "false"] => reader == "flag",
            Form::Choice { .. } => reader == "choice" || reader == "value",
            Form::Triple { .. } => reader == "triple",
            Form::Function { .. } => reader == "function",
            Form::Output { .. } if required => reader == "required_output",
            Form::Output { .. } => reader == "output",
            Form::Size { .. } => reader == "size",
            Form::Value { .. } if required => reader == "required",
            Form::Value { .. } => reader == "value",
        }
    }

    /// A typed struct has a field per setting of its schema, in the schema's order, each read as its form.
    fn matches_its_schema<T: TypedSettings>() {
        let names: Vec<&str> = T::SCHEMA.settings.iter().map(|s| s.name).collect();
        let fields: Vec<&str> = T::FIELDS.iter().map(|(name, _)| *name).collect();
        assert_eq!(fields, names, "the fields of {}'s settings", T::SCHEMA.title());
        for (setting, (name, reader)) in T::SCHEMA.settings.iter().zip(T::FIELDS) {
            assert!(
                reads(reader, &setting.form, setting.required.is_some()),
                "{}: setting '{name}' is read as `{reader}`, not as its form {:?}",
                T::SCHEMA.title(),
                setting.form
            );
        }
    }

    #[test]
    fn every_typed_struct_matches_its_schema() {
        matches_its_schema::<crate::blocks::sphere_trace::SphereTraceSettings>();
        matches_its_schema::<crate::blocks::volume::RenderVolumeSettings>();
        matches_its_schema::<crate::blocks::train::TrainSettings>();
        matches_its_schema::<crate::blocks::train_sdf::TrainSdfSettings>();
        matches_its_schema::<crate::blocks::mesh::MeshSettings>();
        matches_its_schema::<crate::blocks::bake::BakeSettings>();
        matches_its_schema::<crate::blocks::viz::VizSettings>();
    }
}
