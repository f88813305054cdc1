//! Particle file reading and writing: round trips keep every property; malformed files give
//! typed errors naming the place, one by one.

use std::path::{Path, PathBuf};

use fluid_surfels::io::{self, Format, IoError, Location, ply, xyz};
use fluid_surfels::{Attribute, ParticleSet, ScalarKind};
use glam::Vec3;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// A set with every kind of attribute, awkward values included.
fn full_set() -> ParticleSet {
    let n = 7;
    let positions: Vec<Vec3> = (0..n)
        .map(|i| {
            Vec3::new(
                i as f32 * 0.1 + 1e-7,
                -(i as f32) * 3.3e5,
                1.0 / (i as f32 + 3.0),
            )
        })
        .collect();
    let mut set = ParticleSet::from_positions(positions);
    set.ids = Some((0..n as u32).map(|i| i * 1000 + u32::MAX / 2).collect());
    set.masses = Some((0..n).map(|i| 0.25 + i as f32 * 1e-3).collect());
    set.velocities = Some(
        (0..n)
            .map(|i| Vec3::new(i as f32, -0.5, f32::MIN_POSITIVE))
            .collect(),
    );
    set.normals = Some(
        (0..n)
            .map(|i| Vec3::new(i as f32, 1.0, 0.0).normalize())
            .collect(),
    );
    set.colours = Some((0..n).map(|i| [i as u8, 255 - i as u8, 128]).collect());
    let kinds = [
        (ScalarKind::I8, -128.0),
        (ScalarKind::U8, 255.0),
        (ScalarKind::I16, -32768.0),
        (ScalarKind::U16, 65535.0),
        (ScalarKind::I32, -2147483648.0),
        (ScalarKind::U32, 4294967295.0),
        (ScalarKind::F32, 0.1f32 as f64),
        (ScalarKind::F64, std::f64::consts::PI),
    ];
    for (k, (kind, extreme)) in kinds.into_iter().enumerate() {
        set.extra.push(Attribute::scalar(
            format!("extra_{k}"),
            kind,
            (0..n)
                .map(|i| if i == 0 { extreme } else { (i % 3) as f64 })
                .collect(),
        ));
    }
    set
}

#[test]
fn ply_round_trip_keeps_every_property_bit_for_bit() {
    let set = full_set();
    set.validate().unwrap();
    for encoding in [
        ply::Encoding::Ascii,
        ply::Encoding::BinaryLittleEndian,
        ply::Encoding::BinaryBigEndian,
    ] {
        let bytes = ply::to_bytes(&set, encoding);
        let back = ply::parse(&bytes, Path::new("memory.ply")).unwrap();
        assert_eq!(back, set, "{encoding:?}");
    }
    // through the file system, by extension
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.ply");
    io::write_particles(&path, &set, None).unwrap();
    assert_eq!(io::read_particles(&path, None).unwrap(), set);
}

#[test]
fn shipped_ply_files_read_with_their_attributes() {
    let binary = io::read_particles(&data("cube.ply"), None).unwrap();
    assert_eq!(binary.len(), 24);
    assert!(binary.normals.is_none());
    assert!(
        binary
            .positions
            .iter()
            .all(|p| p.abs().max_element() == 1.0)
    );
    let ascii = io::read_particles(&data("cube_normals.ply"), None).unwrap();
    assert_eq!(ascii.len(), 24);
    let normals = ascii.normals.as_ref().unwrap();
    assert!(normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-6));
    // texture coordinates are kept as attributes with their type
    let names: Vec<&str> = ascii.extra.iter().map(|a| a.name.as_str()).collect();
    assert_eq!(names, ["s", "t"]);
    assert_eq!(ascii.extra[0].kind, ScalarKind::F32);
    assert_eq!(ascii.extra[0].values[0], 0.875);
    // same cube in both files: same set of corner positions
    let key = |p: &Vec3| (p.x as i32, p.y as i32, p.z as i32);
    let mut a: Vec<_> = binary.positions.iter().map(key).collect();
    let mut b: Vec<_> = ascii.positions.iter().map(key).collect();
    a.sort();
    b.sort();
    assert_eq!(a, b);
    // the faces of these meshes are read past; writing and reading back keeps the vertices
    let again = ply::parse(
        &ply::to_bytes(&ascii, ply::Encoding::BinaryLittleEndian),
        Path::new("m"),
    )
    .unwrap();
    assert_eq!(again, ascii);
}

fn parse_err(text: &[u8]) -> IoError {
    ply::parse(text, Path::new("bad.ply")).expect_err("malformed input must fail")
}

fn location(e: &IoError) -> Location {
    match e {
        IoError::Parse { location, .. } | IoError::NonFinite { location, .. } => *location,
        IoError::WrongFormat { .. } => Location::Byte(0),
        other => panic!("unexpected error {other}"),
    }
}

const HEADER: &str = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n";

#[test]
fn malformed_ply_headers() {
    let e = parse_err(b"plx\nformat ascii 1.0\n");
    assert!(matches!(e, IoError::WrongFormat { .. }), "{e}");
    assert!(
        e.to_string().contains("bad.ply") && e.to_string().contains("plx"),
        "{e}"
    );
    let e = parse_err(b"ply\nformat ascii 2.0\nend_header\n");
    assert!(e.to_string().contains("version 1.0"), "{e}");
    let e = parse_err(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n");
    assert!(e.to_string().contains("end_header"), "{e}");
    let e =
        parse_err(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty quaternion x\nend_header\n");
    assert_eq!(location(&e), Location::Line(4));
    let e =
        parse_err(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n0\n1\n");
    assert!(e.to_string().contains("x, y and z"), "{e}");
    let e = parse_err(b"ply\nformat ascii 1.0\nelement face 1\nproperty float x\nend_header\n0\n");
    assert!(e.to_string().contains("element vertex"), "{e}");
    let e = parse_err(b"ply\nformat ascii 1.0\nelement vertex two\nend_header\n");
    assert_eq!(location(&e), Location::Line(3));
}

#[test]
fn malformed_ascii_ply_data() {
    // non-numeric text, with its line
    let e = parse_err(format!("{HEADER}0 0 0\n1 one 1\n").as_bytes());
    assert_eq!(location(&e), Location::Line(9));
    assert!(e.to_string().contains("found \"one\""), "{e}");
    // too few values (count says 2, file has 1): refused from the size alone
    let e = parse_err(format!("{HEADER}0 0 0\n").as_bytes());
    assert!(e.to_string().contains("wrong counts or truncated"), "{e}");
    // long enough, but a value short
    let e = parse_err(format!("{HEADER}0.000 0.000 0.000\n1.000 1.000\n").as_bytes());
    assert!(e.to_string().contains("end of file"), "{e}");
    // too many (count says 2, file has 3)
    let e = parse_err(format!("{HEADER}0 0 0\n1 1 1\n2 2 2\n").as_bytes());
    assert_eq!(location(&e), Location::Line(10));
    assert!(e.to_string().contains("wrong counts"), "{e}");
    // NaN and infinite coordinates
    for bad in ["nan", "inf", "-inf", "NaN", "1e39"] {
        let e = parse_err(format!("{HEADER}0 0 0\n1 {bad} 1\n").as_bytes());
        assert!(
            matches!(
                e,
                IoError::NonFinite {
                    index: 1,
                    location: Location::Line(9),
                    ..
                }
            ),
            "{bad}: {e}"
        );
    }
    // integers out of range for their type
    let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n0 0 0 256\n";
    assert!(parse_err(text.as_bytes()).to_string().contains("uchar"));
    // a count that would need far more memory than the file holds is refused before allocating
    let e = parse_err(b"ply\nformat ascii 1.0\nelement vertex 4000000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n");
    assert!(e.to_string().contains("wrong counts or truncated"), "{e}");
}

#[test]
fn malformed_binary_ply_data() {
    let set = full_set();
    let bytes = ply::to_bytes(&set, ply::Encoding::BinaryLittleEndian);
    let header_len = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap()
        + 11;
    // truncated anywhere in the data: an error naming a byte offset inside the file, never a panic
    for cut in header_len..bytes.len() {
        let e = parse_err(&bytes[..cut]);
        match location(&e) {
            Location::Byte(b) => assert!(b as usize <= cut, "cut {cut}: {e}"),
            Location::Line(_) => panic!("cut {cut}: binary data errors give byte offsets: {e}"),
        }
    }
    // trailing garbage: wrong count
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0; 5]);
    assert!(parse_err(&longer).to_string().contains("wrong counts"));
    // NaN and infinity in a binary coordinate, with the byte offset of the value
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut b = bytes.clone();
        let record: usize = 4 * 3 + 4 * 3 + 4 * 3 + 4 + 4 + 3 + (1 + 1 + 2 + 2 + 4 + 4 + 4 + 8);
        let at = header_len + 2 * record + 4; // y of particle 2
        b[at..at + 4].copy_from_slice(&bad.to_le_bytes());
        let e = parse_err(&b);
        assert!(
            matches!(e, IoError::NonFinite { index: 2, location: Location::Byte(o), .. } if o as usize == at),
            "{e}"
        );
    }
    // a list whose length runs past the end of the file
    let mut text = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n".to_vec();
    text.extend_from_slice(&[0; 12]);
    text.push(200);
    text.extend_from_slice(&[0; 8]);
    assert!(parse_err(&text).to_string().contains("list length"));
}

#[test]
fn text_round_trips_and_errors() {
    let set = full_set();
    // whitespace xyz: positions and normals, exactly (shortest round-trip decimals)
    let text = xyz::to_string(&set, xyz::Delimiter::Space);
    let back = xyz::parse(text.as_bytes(), Path::new("p.xyz")).unwrap();
    assert_eq!(back.positions, set.positions);
    assert_eq!(back.normals, set.normals);
    // csv with a header: every attribute but colours
    let text = xyz::to_string(&set, xyz::Delimiter::Comma);
    let back = xyz::parse(text.as_bytes(), Path::new("p.csv")).unwrap();
    assert_eq!(back.positions, set.positions);
    assert_eq!(back.velocities, set.velocities);
    assert_eq!(back.masses, set.masses);
    assert_eq!(back.ids, set.ids);
    for (a, b) in back.extra.iter().zip(&set.extra) {
        assert_eq!((a.name.as_str(), &a.values), (b.name.as_str(), &b.values));
    }
    // comments and blank lines are skipped; commas or spaces both separate
    let ok = xyz::parse(b"# particles\n\n0 0 0\n1,2,3\n", Path::new("p.xyz")).unwrap();
    assert_eq!(ok.positions, vec![Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0)]);

    let err = |t: &str| xyz::parse(t.as_bytes(), Path::new("bad.xyz")).unwrap_err();
    let e = err("0 0 0\n1 2\n");
    assert!(
        matches!(
            e,
            IoError::Parse {
                location: Location::Line(2),
                ..
            }
        ),
        "{e}"
    );
    let e = err("0 0\n");
    assert!(e.to_string().contains("3 columns"), "{e}");
    let e = err("x,y,z\n0,0,0\n1,zero,1\n");
    assert!(
        matches!(
            e,
            IoError::Parse {
                location: Location::Line(3),
                ..
            }
        ),
        "{e}"
    );
    let e = err("0 0 0\n1 nan 1\n");
    assert!(
        matches!(
            e,
            IoError::NonFinite {
                index: 1,
                location: Location::Line(2),
                ..
            }
        ),
        "{e}"
    );
    let e = err("a,b,c\n0,0,0\n");
    assert!(e.to_string().contains("x, y and z"), "{e}");
    let e = xyz::parse(&[0xff, 0xfe, 0x00, 0x01], Path::new("raw.xyz")).unwrap_err();
    assert!(e.to_string().contains("binary"), "{e}");
}

#[test]
fn formats_by_extension_and_file_errors() {
    assert_eq!(Format::from_path(Path::new("a.PLY")).unwrap(), Format::Ply);
    assert_eq!(Format::from_path(Path::new("a.csv")).unwrap(), Format::Csv);
    assert_eq!(
        Format::from_path(Path::new("d/f_0001.vtk")).unwrap(),
        Format::Vtk
    );
    assert_eq!(
        Format::from_path(Path::new("f.bgeo.gz")).unwrap(),
        Format::Bgeo
    );
    assert_eq!(Format::from_path(Path::new("f.vtu")).unwrap(), Format::Vtu);
    let e = Format::from_path(Path::new("a.abc")).unwrap_err();
    assert!(
        matches!(e, IoError::UnknownFormat { .. }) && e.to_string().contains("abc"),
        "{e}"
    );
    assert!(Format::from_path(Path::new("a.gz")).is_err());
    let e = io::read_particles(Path::new("/nonexistent/p.ply"), None).unwrap_err();
    assert!(
        matches!(e, IoError::Os { .. }) && e.to_string().contains("/nonexistent/p.ply"),
        "{e}"
    );
    // an invalid set is refused before anything is written
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ply");
    let mut bad = full_set();
    bad.positions[0].x = f32::NAN;
    assert!(matches!(
        io::write_particles(&path, &bad, None),
        Err(IoError::InvalidSet { .. })
    ));
    assert!(!path.exists());
}
