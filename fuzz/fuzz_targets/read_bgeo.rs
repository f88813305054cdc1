//! Any bytes given to the Bgeo reader give a particle set or an error, never a panic, a hang or
//! an allocation the input does not justify; errors are short and free of control characters.
#![no_main]

use std::path::Path;

use fluid_surfels::io::{Format, parse_bytes};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Err(e) = parse_bytes(Format::Bgeo, data, Path::new("fuzz")) {
        // a message a user can read: no control character from the file, one short line
        let text = e.to_string();
        assert!(
            !text.chars().any(char::is_control) && text.chars().count() <= 300,
            "{text:?}"
        );
    }
});
