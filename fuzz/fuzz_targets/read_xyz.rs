//! Any bytes given to the text (XYZ, CSV) and raw-triplet readers give a particle set or an
//! error, never a panic.
#![no_main]

use std::path::Path;

use fluid_surfels::io::{Format, parse_bytes};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Err(e) = parse_bytes(Format::Xyz, data, Path::new("fuzz")) {
        // a message a user can read: no control character from the file, one short line
        let text = e.to_string();
        assert!(
            !text.chars().any(char::is_control) && text.chars().count() <= 300,
            "{text:?}"
        );
    }
    let _ = parse_bytes(Format::Csv, data, Path::new("fuzz"));
    let _ = parse_bytes(Format::XyzRaw, data, Path::new("fuzz"));
});
