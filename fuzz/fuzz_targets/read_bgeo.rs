//! Any bytes given to the Bgeo reader give a particle set or an error, never a panic, a hang or
//! an allocation the input does not justify.
#![no_main]

use std::path::Path;

use fluid_surfels::io::{Format, parse_bytes};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = parse_bytes(Format::Bgeo, data, Path::new("fuzz"));
});
