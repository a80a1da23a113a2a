//! Pictures and videos written: 8-bit images, PNG and GIF files ([`image_out`]), MP4 videos ([`video`]),
//! text labels drawn into images ([`label`]) and the course's teaching images ([`viz`]).

pub mod frame;
pub mod image_out;
pub mod label;
pub mod video;
pub mod viz;
