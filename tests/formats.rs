//! Every reader and writer: the shipped SPH files, round trips across formats, files checked by
//! another tool's reader (vtkio), and malformed files of every kind.

use std::path::{Path, PathBuf};

use fluid_surfels::io::{self, Format, IoError, Location, vtu};
use fluid_surfels::{Attribute, ParticleSet, ScalarKind};
use glam::Vec3;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

#[test]
fn shipped_sph_files_read_with_counts_and_attributes() {
    // SPlisHSPlasH: legacy VTK 4.1 BINARY, vertex cells, FIELD with id and velocity
    let dam =
        io::read_particles(&data("double_dam_break_frame_26_4732_particles.vtk"), None).unwrap();
    assert_eq!(dam.len(), 4732);
    let ids = dam.ids.as_ref().expect("the id array becomes ids");
    let mut sorted = ids.clone();
    sorted.sort_unstable();
    sorted.dedup();
    assert_eq!(sorted.len(), 4732, "ids are unique");
    let v = dam
        .velocities
        .as_ref()
        .expect("the velocity array becomes velocities");
    assert!(v.iter().all(|v| v.is_finite()) && v.iter().any(|v| v.length() > 0.1));
    // the simulation's domain: a 3 x 1 x 3 box around the origin (spacing 0.05)
    let (lo, hi) = dam.bounds().unwrap();
    assert!(
        lo.cmpgt(Vec3::new(-1.6, -0.1, -1.6)).all() && hi.cmplt(Vec3::new(1.6, 1.1, 1.6)).all(),
        "{lo} {hi}"
    );
    // particles of radius 0.025: nearest neighbours a little closer than 2r in the flowing
    // frame; the density-based spacing is larger than 2r in this thin sheet (see
    // `neighbours::spacing_estimate`)
    let e = fluid_surfels::neighbours::spacing_estimate(&dam.positions).unwrap();
    println!("double dam break: {e:?}");
    assert!((0.03..0.05).contains(&e.nearest), "{e:?}");
    assert!((0.05..0.08).contains(&e.spacing), "{e:?}");

    // ParaView: legacy VTK 5.1 ASCII with OFFSETS/CONNECTIVITY, double points
    let cube = io::read_particles(&data("cube_8_particles.vtk"), None).unwrap();
    assert_eq!(cube.len(), 8);
    assert_eq!(cube.positions[1], Vec3::new(0.5, 0.4995095, 1.0));

    // isolated particles, legacy BINARY with empty POINT_DATA/CELL_DATA sections
    let free = io::read_particles(&data("free_particles_125_particles.vtk"), None).unwrap();
    assert_eq!(free.len(), 125);
    assert!(free.extra.is_empty());

    // partio's gzipped BGEO. The data README says it carries id, density and velocity; the file
    // itself declares no point attribute (header: 24,389 points, 0 attributes, 16-byte records,
    // which is also its decompressed size of 41 + 24,389 x 16 + 2 bytes), so only positions exist.
    let bgeo = io::read_particles(&data("dam_break_frame_23_24389_particles.bgeo"), None).unwrap();
    assert_eq!(bgeo.len(), 24_389);
    assert!(bgeo.ids.is_none() && bgeo.velocities.is_none() && bgeo.extra.is_empty());
    let (lo, hi) = bgeo.bounds().unwrap();
    assert!(lo.y > 0.0 && hi.y < 4.0, "{lo} {hi}");

    // PLY from Blender
    assert_eq!(
        io::read_particles(&data("cube.ply"), None).unwrap().len(),
        24
    );
    assert_eq!(
        io::read_particles(&data("cube_normals.ply"), None)
            .unwrap()
            .len(),
        24
    );
}

/// A set with every kind of attribute the generic formats carry.
fn rich_set(n: usize) -> ParticleSet {
    let positions: Vec<Vec3> = (0..n)
        .map(|i| {
            Vec3::new(
                (i as f32 * 0.37).sin() * 1.5,
                i as f32 * 1e-3 + 0.1,
                -(i as f32).sqrt() / 7.0,
            )
        })
        .collect();
    let mut set = ParticleSet::from_positions(positions);
    set.ids = Some((0..n as u32).map(|i| i * 7 + 3).collect());
    set.velocities = Some(
        (0..n)
            .map(|i| Vec3::new(i as f32 * 0.1, -1.0 / (i as f32 + 1.0), 0.25))
            .collect(),
    );
    set.masses = Some((0..n).map(|i| 1.0 + i as f32 * 1e-4).collect());
    set.extra.push(Attribute::scalar(
        "density",
        ScalarKind::F32,
        (0..n).map(|i| (1000.0 + i as f32 * 0.5) as f64).collect(),
    ));
    set.extra.push(Attribute {
        name: "vorticity".into(),
        kind: ScalarKind::F32,
        components: 3,
        values: (0..3 * n)
            .map(|k| ((k as f32) * 0.01).cos() as f64)
            .collect(),
    });
    set.extra.push(Attribute::scalar(
        "phase",
        ScalarKind::I32,
        (0..n).map(|i| (i % 4) as f64 - 1.0).collect(),
    ));
    set
}

#[test]
fn positions_agree_across_formats() {
    let set = rich_set(300);
    let dir = tempfile::tempdir().unwrap();
    for format in Format::ALL {
        let name = format!(
            "p.{}",
            match format {
                Format::XyzRaw => "bin",
                Format::Bgeo => "bgeo",
                f => f.name(),
            }
        );
        let path = dir.path().join(name);
        io::write_particles(&path, &set, Some(format)).unwrap();
        let back = io::read_particles(&path, Some(format)).unwrap();
        assert_eq!(back.len(), set.len(), "{format:?}");
        // binary formats and the shortest-decimal text writers both give the exact f32 back
        assert_eq!(back.positions, set.positions, "{format:?}: positions");
        match format {
            Format::Ply | Format::Vtk | Format::Vtu | Format::Bgeo => {
                assert_eq!(back.ids, set.ids, "{format:?}: ids");
                assert_eq!(back.velocities, set.velocities, "{format:?}: velocities");
                assert_eq!(back.masses, set.masses, "{format:?}: masses");
                if format == Format::Ply {
                    // PLY holds scalars: the vector attribute comes back as three columns
                    assert!(back.attribute("vorticity_y").is_some());
                } else {
                    assert_eq!(back.extra, set.extra, "{format:?}: extra attributes");
                }
            }
            Format::Csv => {
                assert_eq!(back.velocities, set.velocities);
                assert_eq!(back.ids, set.ids);
            }
            Format::Xyz | Format::XyzRaw | Format::Json => {}
        }
    }
    // VTU in each of its encodings
    for encoding in [
        vtu::Encoding::Ascii,
        vtu::Encoding::Base64,
        vtu::Encoding::RawAppended,
    ] {
        let bytes = vtu::to_bytes_with(&set, encoding);
        let back = vtu::parse(&bytes, Path::new("m.vtu")).unwrap();
        assert_eq!(back.positions, set.positions, "{encoding:?}");
        assert_eq!(back.extra, set.extra, "{encoding:?}");
        assert_eq!(back.ids, set.ids, "{encoding:?}");
    }
    // gzipped BGEO by extension
    let gz = dir.path().join("p.bgeo.gz");
    io::write_particles(&gz, &set, None).unwrap();
    assert_eq!(&std::fs::read(&gz).unwrap()[..2], &[0x1f, 0x8b]);
    assert_eq!(
        io::read_particles(&gz, None).unwrap().positions,
        set.positions
    );
}

#[test]
fn written_vtk_files_open_in_vtkio() {
    let set = rich_set(50);
    let dir = tempfile::tempdir().unwrap();
    let legacy = dir.path().join("p.vtk");
    io::write_particles(&legacy, &set, None).unwrap();
    let vtk = vtkio::Vtk::import(&legacy)
        .unwrap_or_else(|e| panic!("vtkio rejects our legacy VTK: {e:?}"));
    let text = format!("{vtk:?}");
    assert!(
        text.contains("velocity") && text.contains("density"),
        "arrays missing in {}",
        &text[..text.len().min(400)]
    );
    // vtkio parses inline base64 and ascii VTU (not raw appended data, which ParaView reads)
    for encoding in [vtu::Encoding::Base64, vtu::Encoding::Ascii] {
        let xml = dir.path().join("p.vtu");
        std::fs::write(&xml, vtu::to_bytes_with(&set, encoding)).unwrap();
        let vtk = vtkio::Vtk::import(&xml)
            .unwrap_or_else(|e| panic!("vtkio rejects our {encoding:?} VTU: {e:?}"));
        assert!(format!("{vtk:?}").contains("vorticity"), "{encoding:?}");
    }
}

fn gzip(bytes: &[u8], level: flate2::Compression) -> Vec<u8> {
    use std::io::Write;
    let mut e = flate2::write::GzEncoder::new(Vec::new(), level);
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

fn parse(format: Format, bytes: &[u8]) -> Result<ParticleSet, IoError> {
    io::parse_bytes(format, bytes, Path::new("bad.file"))
}

#[test]
fn every_reader_survives_truncation_at_every_percent() {
    let set = rich_set(200);
    for format in Format::ALL {
        let bytes = io::to_bytes(format, &set, Path::new("x")).unwrap();
        let mut errors = 0;
        for pct in 1..100 {
            let cut = bytes.len() * pct / 100;
            match parse(format, &bytes[..cut]) {
                Err(e) => {
                    errors += 1;
                    assert!(
                        e.to_string().contains("bad.file"),
                        "{format:?} at {pct} %: {e}"
                    );
                }
                // text formats cut at a line end are complete files of fewer particles
                Ok(s) => assert!(
                    matches!(format, Format::Xyz | Format::Csv) && s.len() < set.len()
                        || format == Format::XyzRaw && s.len() == cut / 12,
                    "{format:?} at {pct} % read {} particles without an error",
                    s.len()
                ),
            }
        }
        println!("{format:?}: {errors} of 99 truncations gave an error");
        if !matches!(format, Format::Xyz | Format::Csv | Format::XyzRaw) {
            assert_eq!(errors, 99, "{format:?}");
        }
    }
    // gzipped BGEO cut short
    let gz = gzip(
        &io::to_bytes(Format::Bgeo, &set, Path::new("x")).unwrap(),
        flate2::Compression::default(),
    );
    for pct in 1..100 {
        assert!(
            parse(Format::Bgeo, &gz[..gz.len() * pct / 100]).is_err(),
            "gz at {pct} %"
        );
    }
}

#[test]
fn wrong_magic_is_named() {
    let ply = io::to_bytes(Format::Ply, &rich_set(3), Path::new("x")).unwrap();
    for format in [Format::Vtk, Format::Vtu, Format::Bgeo, Format::Json] {
        let e = parse(format, &ply).unwrap_err();
        assert!(matches!(e, IoError::WrongFormat { .. }), "{format:?}: {e}");
        assert!(e.to_string().contains("PLY"), "{format:?}: {e}");
    }
    let vtk = std::fs::read(data("cube_8_particles.vtk")).unwrap();
    let e = parse(Format::Ply, &vtk).unwrap_err();
    assert!(e.to_string().contains("legacy VTK"), "{e}");
    let bgeo = std::fs::read(data("dam_break_frame_23_24389_particles.bgeo")).unwrap();
    let e = parse(Format::Vtk, &bgeo).unwrap_err();
    assert!(e.to_string().contains("gzip"), "{e}");
    // a text .xyz that is really binary says how to read raw triplets
    let e = parse(
        Format::Xyz,
        &io::to_bytes(Format::XyzRaw, &rich_set(5), Path::new("x")).unwrap(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("xyz-raw"), "{e}");
}

#[test]
fn unsupported_versions_and_types() {
    let e = parse(
        Format::Vtk,
        b"# vtk DataFile Version 9.0\nt\nASCII\nDATASET POLYDATA\n",
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            IoError::Unsupported {
                location: Location::Line(1),
                ..
            }
        ),
        "{e}"
    );
    let e = parse(
        Format::Vtk,
        b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET STRUCTURED_POINTS\n",
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            IoError::Unsupported {
                location: Location::Line(4),
                ..
            }
        ),
        "{e}"
    );
    let mut bgeo = io::to_bytes(Format::Bgeo, &rich_set(3), Path::new("x")).unwrap();
    bgeo[8] = 4; // version 4
    let e = parse(Format::Bgeo, &bgeo).unwrap_err();
    assert!(e.to_string().contains("version"), "{e}");
    let e = parse(Format::Bgeo, &[0x7f, b'N', b'S', b'J', 0, 0]).unwrap_err();
    assert!(e.to_string().contains("new-style"), "{e}");
    let e = parse(
        Format::Vtu,
        b"<?xml version=\"1.0\"?><VTKFile type=\"ImageData\"></VTKFile>",
    )
    .unwrap_err();
    assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
    let e = parse(
        Format::Vtu,
        b"<VTKFile type=\"UnstructuredGrid\" compressor=\"vtkLZ4DataCompressor\"></VTKFile>",
    )
    .unwrap_err();
    assert!(e.to_string().contains("LZ4"), "{e}");
}

#[test]
fn wrong_counts_are_caught_where_they_are() {
    // VTK: POINTS says 3, two given
    let text =
        b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0 0 1 1 1\n";
    let e = parse(Format::Vtk, text).unwrap_err();
    assert!(e.location().is_some(), "{e}");
    // VTK: POINT_DATA count differs from POINTS
    let text = b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n0 0 0 1 1 1\nPOINT_DATA 3\n";
    let e = parse(Format::Vtk, text).unwrap_err();
    assert!(
        matches!(e, IoError::Parse { .. }) && e.location() == Some(Location::Line(7)),
        "{e}"
    );
    // VTK: non-numeric value with its line
    let text =
        b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n0 0 0\n1 x 1\n";
    let e = parse(Format::Vtk, text).unwrap_err();
    assert!(
        matches!(e, IoError::Parse { .. }) && e.location() == Some(Location::Line(7)),
        "{e}"
    );
    // VTK: NaN coordinates
    let text =
        b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\nPOINTS 2 float\n0 0 0\n1 nan 1\n";
    assert!(matches!(
        parse(Format::Vtk, text),
        Err(IoError::NonFinite { index: 1, .. })
    ));
    // BGEO: point count larger than the data
    let mut bgeo = io::to_bytes(Format::Bgeo, &rich_set(10), Path::new("x")).unwrap();
    bgeo[9..13].copy_from_slice(&20i32.to_be_bytes());
    let e = parse(Format::Bgeo, &bgeo).unwrap_err();
    assert!(e.to_string().contains("wrong count"), "{e}");
    // VTU: fewer ascii values than NumberOfPoints requires
    let bytes = vtu::to_bytes_with(&rich_set(4), vtu::Encoding::Ascii);
    let text = String::from_utf8(bytes)
        .unwrap()
        .replace("NumberOfPoints=\"4\"", "NumberOfPoints=\"5\"");
    let e = parse(Format::Vtu, text.as_bytes()).unwrap_err();
    assert!(
        matches!(
            e,
            IoError::Parse {
                location: Location::Byte(_),
                ..
            }
        ),
        "{e}"
    );
    // JSON: not triplets
    let e = parse(Format::Json, b"[[0, 0, 0], [1, 2]]").unwrap_err();
    assert!(
        matches!(e, IoError::Parse { .. }) && e.location() == Some(Location::Line(1)),
        "{e}"
    );
    // raw xyz: not a multiple of 12 bytes
    let e = parse(Format::XyzRaw, &[0u8; 25]).unwrap_err();
    assert!(
        matches!(e, IoError::Parse { .. }) && e.location() == Some(Location::Byte(24)),
        "{e}"
    );
}

#[test]
fn counts_beyond_memory_and_gzip_bombs_are_refused_without_allocating() {
    // headers declaring ~2^31 x 3 values: more than the file, or more than the machine
    let e = parse(Format::Vtk, b"# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\nPOINTS 4000000000 float\n\x00\x00").unwrap_err();
    assert!(e.to_string().contains("wrong count or truncated"), "{e}");
    let mut bgeo = io::to_bytes(Format::Bgeo, &rich_set(2), Path::new("x")).unwrap();
    bgeo[9..13].copy_from_slice(&i32::MAX.to_be_bytes());
    assert!(parse(Format::Bgeo, &bgeo).is_err());
    // gzipped BGEO whose header says 2^31 points: refused from the header, more than the
    // gzip stream can inflate to
    let gz = gzip(&bgeo, flate2::Compression::default());
    let e = parse(Format::Bgeo, &gz).unwrap_err();
    assert!(e.to_string().contains("gzipped bytes can hold"), "{e}");
    // a gzip bomb: a 2-point header followed by 2 GiB of zeros (about 2 MiB compressed)
    let small = io::to_bytes(Format::Bgeo, &rich_set(2), Path::new("x")).unwrap();
    let mut bomb = Vec::new();
    {
        use std::io::Write;
        let mut e = flate2::write::GzEncoder::new(&mut bomb, flate2::Compression::best());
        e.write_all(&small).unwrap();
        let zeros = vec![0u8; 1 << 20];
        for _ in 0..2048 {
            e.write_all(&zeros).unwrap();
        }
        e.finish().unwrap();
    }
    assert!(bomb.len() < 4 << 20, "{}", bomb.len());
    let e = parse(Format::Bgeo, &bomb).unwrap_err();
    assert!(e.to_string().contains("gzip bomb"), "{e}");
    // VTU compression header claiming terabytes
    let xml = b"<VTKFile type=\"UnstructuredGrid\" compressor=\"vtkZLibDataCompressor\" header_type=\"UInt64\"><UnstructuredGrid><Piece NumberOfPoints=\"1\"><Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points></Piece></UnstructuredGrid><AppendedData encoding=\"raw\">_";
    let mut v = xml.to_vec();
    for value in [1u64, 1 << 40, 1 << 40, 10] {
        v.extend_from_slice(&value.to_le_bytes());
    }
    v.extend_from_slice(b"</AppendedData></VTKFile>");
    let e = parse(Format::Vtu, &v).unwrap_err();
    assert!(e.to_string().contains("inflates 1032x at most"), "{e}");
}

/// The values a lying size field is set to: zero, 2^31, 2^32 - 1 and 2^63.
const FIELD_VALUES: [u64; 4] = [0, 1 << 31, u32::MAX as u64, 1 << 63];

/// Offsets where a file's blocks begin: line starts (keywords of text headers), XML tags, the
/// appended data's start and every array's offset in it.
fn block_boundaries(bytes: &[u8]) -> Vec<usize> {
    let mut at: Vec<usize> = vec![0, bytes.len()];
    let text_part = bytes.len().min(4096);
    for (i, &b) in bytes[..text_part].iter().enumerate() {
        if b == b'\n' || b == b'<' {
            at.push(i + 1);
        }
    }
    let find = |needle: &[u8]| bytes.windows(needle.len()).position(|w| w == needle);
    if let Some(tag) = find(b"<AppendedData") {
        let start = tag + bytes[tag..].iter().position(|&c| c == b'_').unwrap_or(0) + 1;
        at.push(start);
        let xml = String::from_utf8_lossy(&bytes[..tag]);
        for part in xml.split("offset=\"").skip(1) {
            if let Some(o) = part.split('"').next().and_then(|o| o.parse::<usize>().ok()) {
                at.push(start + o);
            }
        }
    }
    at.retain(|&k| k <= bytes.len());
    at.sort_unstable();
    at.dedup();
    at
}

/// Every structured mutation of a file: truncation at, one and two before and one after every
/// block boundary; a byte deleted and one inserted there and at a stride through the whole file
/// (inside the binary blocks); every text number in the header and every binary word (32- and
/// 64-bit, both byte orders) at a boundary set to each of [`FIELD_VALUES`].
fn structured_mutations(bytes: &[u8]) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let bounds = block_boundaries(bytes);
    let stride = (bytes.len() / 60).max(1);
    let mut edits: Vec<usize> = bounds.clone();
    edits.extend((0..bytes.len()).step_by(stride));
    for &b in &bounds {
        // two before: a binary block followed by its line end, one byte short
        for cut in [b.saturating_sub(2), b.saturating_sub(1), b, b + 1] {
            if cut < bytes.len() {
                out.push(bytes[..cut].to_vec());
            }
        }
    }
    for &at in &edits {
        if at < bytes.len() {
            let mut d = bytes.to_vec();
            d.remove(at);
            out.push(d);
            let mut i = bytes.to_vec();
            i.insert(at, b'7');
            out.push(i);
        }
    }
    // decimal numbers in the text part (counts, sizes, offsets)
    let text_part = bytes.len().min(4096);
    let mut k = 0;
    while k < text_part {
        if bytes[k].is_ascii_digit() && (k == 0 || !bytes[k - 1].is_ascii_alphanumeric()) {
            let end = k + bytes[k..].iter().take_while(|b| b.is_ascii_digit()).count();
            for v in FIELD_VALUES {
                let mut m = bytes[..k].to_vec();
                m.extend_from_slice(v.to_string().as_bytes());
                m.extend_from_slice(&bytes[end..]);
                out.push(m);
            }
            k = end;
        } else {
            k += 1;
        }
    }
    // binary words at block boundaries and just after them (the size headers of blocks)
    for &b in &bounds {
        for at in [b, b + 4, b + 8, b + 12] {
            for v in FIELD_VALUES {
                for word in [
                    (v as u32).to_le_bytes().to_vec(),
                    (v as u32).to_be_bytes().to_vec(),
                    v.to_le_bytes().to_vec(),
                    v.to_be_bytes().to_vec(),
                ] {
                    if at + word.len() <= bytes.len() {
                        let mut m = bytes.to_vec();
                        m[at..at + word.len()].copy_from_slice(&word);
                        out.push(m);
                    }
                }
            }
        }
    }
    out
}

/// An error message a user can read: no control character, at most 300 characters.
fn assert_readable(e: &IoError, what: &str) {
    let text = e.to_string();
    assert!(
        !text.chars().any(char::is_control) && text.chars().count() <= 300,
        "{what}: {} characters: {text:?}",
        text.chars().count()
    );
}

#[test]
fn mutated_files_never_panic() {
    use rand::{Rng, SeedableRng};
    let seed: u64 = std::env::var("FLUID_SURFELS_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(7);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let start = std::time::Instant::now();
    let set = rich_set(20);
    let mut cases: Vec<(Format, Vec<u8>)> = Format::ALL
        .iter()
        .map(|&f| (f, io::to_bytes(f, &set, Path::new("x")).unwrap()))
        .collect();
    for encoding in [vtu::Encoding::Ascii, vtu::Encoding::Base64] {
        cases.push((Format::Vtu, vtu::to_bytes_with(&set, encoding)));
    }
    for (compressed, header64) in [(false, true), (true, false), (true, true)] {
        cases.push((
            Format::Vtu,
            appended_base64(&set, compressed, header64, Streams::EachBlock),
        ));
    }
    let coords: Vec<u8> = set
        .positions
        .iter()
        .flat_map(|p| p.to_array())
        .flat_map(f32::to_le_bytes)
        .collect();
    let (header, blocks) = zlib_blocks(&coords, 100, false);
    cases.push((
        Format::Vtu,
        vtu_raw_zlib(set.len() as u64, &header, &blocks.concat()),
    ));
    for (_, bytes, _) in binary_vtk_dialects(&set) {
        cases.push((Format::Vtk, bytes));
    }
    cases.push((
        Format::Bgeo,
        gzip(
            &io::to_bytes(Format::Bgeo, &set, Path::new("x")).unwrap(),
            flate2::Compression::fast(),
        ),
    ));
    cases.push((
        Format::Vtk,
        std::fs::read(data("cube_8_particles.vtk")).unwrap(),
    ));
    cases.push((
        Format::Ply,
        std::fs::read(data("cube_normals.ply")).unwrap(),
    ));
    let mut parsed = 0;
    let mut total = 0;
    let mut check = |format: Format, bytes: &[u8], what: &dyn Fn() -> String| {
        let result = std::panic::catch_unwind(|| io::parse_bytes(format, bytes, Path::new("m")));
        let Ok(result) = result else {
            panic!(
                "seed {seed} (FLUID_SURFELS_SEED): {format:?} {} panicked",
                what()
            );
        };
        match result {
            Ok(_) => parsed += 1,
            Err(e) => assert_readable(&e, &format!("{format:?} {}", what())),
        }
        total += 1;
    };
    for (case, (format, original)) in cases.iter().enumerate() {
        for round in 0..400 {
            let mut bytes = original.clone();
            for _ in 0..rng.random_range(1..4) {
                let at = rng.random_range(0..bytes.len().max(1));
                match rng.random_range(0..5) {
                    0 if !bytes.is_empty() => bytes[at] ^= 1 << rng.random_range(0..8),
                    1 if !bytes.is_empty() => {
                        bytes[at] = [0, 0xff, b'9', b'-', b'\n', b' ', 0x1b][rng.random_range(0..7)]
                    }
                    2 if !bytes.is_empty() => {
                        bytes.remove(at);
                    }
                    3 => bytes.insert(at.min(bytes.len()), rng.random()),
                    _ => bytes.truncate(at),
                }
            }
            check(*format, &bytes, &|| format!("case {case} round {round}"));
        }
        for (k, m) in structured_mutations(original).iter().enumerate() {
            check(*format, m, &|| {
                format!("case {case} structured mutation {k}")
            });
        }
    }
    println!(
        "{total} mutated files ({} cases), {parsed} still read, {:.1} s",
        cases.len(),
        start.elapsed().as_secs_f64()
    );
}

#[test]
fn legacy_vtk_variants() {
    // ASCII POLYDATA with VERTICES, SCALARS (with a lookup table), VECTORS, a FIELD block and
    // cell data that is read past
    let text = b"# vtk DataFile Version 3.0
particles
ASCII
DATASET POLYDATA
POINTS 3 float
0 0 0  1 0 0
0 1 0
VERTICES 3 6
1 0 1 1 1 2
POINT_DATA 3
SCALARS density float 1
LOOKUP_TABLE default
1000 1001.5 999
VECTORS velocity double
0 0 -1 0 0 -2 0.5 0 0
FIELD extra 2
mass 1 3 float
0.1 0.2 0.3
id 1 3 int
7 8 9
CELL_DATA 3
SCALARS cell_thing int
LOOKUP_TABLE default
1 2 3
";
    let s = io::parse_bytes(Format::Vtk, text, Path::new("p.vtk")).unwrap();
    assert_eq!(s.len(), 3);
    assert_eq!(s.ids, Some(vec![7, 8, 9]));
    assert_eq!(s.masses, Some(vec![0.1, 0.2, 0.3]));
    assert_eq!(s.velocities.as_ref().unwrap()[1], Vec3::new(0.0, 0.0, -2.0));
    assert_eq!(
        s.attribute("density").unwrap().values,
        vec![1000.0, 1001.5, 999.0]
    );
    assert!(s.attribute("cell_thing").is_none());

    // BINARY 5.1 with 64-bit OFFSETS/CONNECTIVITY, as ParaView 5.10+ writes it
    let mut b = b"# vtk DataFile Version 5.1\nvtk output\nBINARY\nDATASET UNSTRUCTURED_GRID\nPOINTS 2 double\n".to_vec();
    for v in [0.5f64, 1.0, 1.5, -2.0, 0.0, 3.25] {
        b.extend_from_slice(&v.to_be_bytes());
    }
    b.extend_from_slice(b"\nCELLS 3 2\nOFFSETS vtktypeint64\n");
    for v in [0i64, 1, 2] {
        b.extend_from_slice(&v.to_be_bytes());
    }
    b.extend_from_slice(b"\nCONNECTIVITY vtktypeint64\n");
    for v in [0i64, 1] {
        b.extend_from_slice(&v.to_be_bytes());
    }
    b.extend_from_slice(b"\nCELL_TYPES 2\n");
    for v in [1i32, 1] {
        b.extend_from_slice(&v.to_be_bytes());
    }
    b.extend_from_slice(b"\nPOINT_DATA 2\nFIELD FieldData 1\nid 1 2 vtktypeint64\n");
    for v in [40i64, 41] {
        b.extend_from_slice(&v.to_be_bytes());
    }
    b.extend_from_slice(b"\nMETADATA\nINFORMATION 0\n\n");
    let s = io::parse_bytes(Format::Vtk, &b, Path::new("p.vtk")).unwrap();
    assert_eq!(
        s.positions,
        vec![Vec3::new(0.5, 1.0, 1.5), Vec3::new(-2.0, 0.0, 3.25)]
    );
    // 64-bit ids are kept as a (double) attribute, not mistaken for 32-bit ids
    assert_eq!(s.attribute("id").unwrap().values, vec![40.0, 41.0]);
}

#[test]
fn vtu_compressed_and_poly_data() {
    use base64::Engine as _;
    let b64 = base64::engine::general_purpose::STANDARD;
    let points: Vec<f32> = (0..300).map(|i| i as f32 * 0.25 - 7.0).collect();
    let raw: Vec<u8> = points.iter().flat_map(|v| v.to_le_bytes()).collect();
    let (header, blocks) = zlib_blocks(&raw, 256, false);
    let blocks = blocks.concat();
    let expected: Vec<Vec3> = points
        .chunks(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect();
    // inline base64, header and data encoded apart (as VTK does when compressing)
    let inline = format!(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt32\" compressor=\"vtkZLibDataCompressor\">\n<PolyData><Piece NumberOfPoints=\"100\" NumberOfVerts=\"0\">\n<Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"binary\">\n{}{}\n</DataArray></Points>\n</Piece></PolyData></VTKFile>\n",
        b64.encode(&header),
        b64.encode(&blocks)
    );
    let s = io::parse_bytes(Format::Vtu, inline.as_bytes(), Path::new("p.vtp")).unwrap();
    assert_eq!(s.positions, expected);
    // raw appended compressed
    let mut file = b"<VTKFile type=\"UnstructuredGrid\" byte_order=\"LittleEndian\" compressor=\"vtkZLibDataCompressor\"><UnstructuredGrid><Piece NumberOfPoints=\"100\" NumberOfCells=\"0\"><Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points></Piece></UnstructuredGrid><AppendedData encoding=\"raw\">_".to_vec();
    file.extend_from_slice(&header);
    file.extend_from_slice(&blocks);
    file.extend_from_slice(b"</AppendedData></VTKFile>");
    let s = io::parse_bytes(Format::Vtu, &file, Path::new("p.vtu")).unwrap();
    assert_eq!(s.positions, expected);
    // a corrupted compressed block is an error, not garbage
    let mut bad = file.clone();
    let at = bad.len() - 40;
    bad[at] ^= 0xff;
    assert!(io::parse_bytes(Format::Vtu, &bad, Path::new("p.vtu")).is_err());
}

/// zlib-compresses `data` into VTK's block layout: the header (block count, block size, last
/// block size, compressed sizes; `u32` or `u64` little-endian) and each compressed block.
fn zlib_blocks(data: &[u8], block: usize, header64: bool) -> (Vec<u8>, Vec<Vec<u8>>) {
    use std::io::Write;
    let chunks: Vec<&[u8]> = data.chunks(block).collect();
    let compressed: Vec<Vec<u8>> = chunks
        .iter()
        .map(|c| {
            let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
            e.write_all(c).unwrap();
            e.finish().unwrap()
        })
        .collect();
    let last = chunks.last().map_or(0, |c| c.len());
    let mut header = Vec::new();
    let mut put = |v: usize| {
        if header64 {
            header.extend_from_slice(&(v as u64).to_le_bytes())
        } else {
            header.extend_from_slice(&(v as u32).to_le_bytes())
        }
    };
    for v in [chunks.len(), block, if last == block { 0 } else { last }] {
        put(v);
    }
    for c in &compressed {
        put(c.len());
    }
    (header, compressed)
}

/// How the base64 streams of a compressed array are cut.
#[derive(Clone, Copy, Debug)]
enum Streams {
    /// Header, then all blocks as one stream.
    HeaderAndBlocks,
    /// Header, then each block its own stream.
    EachBlock,
}

/// The positions and some point arrays of `set` as a VTU file with `<AppendedData
/// encoding="base64">`, every array its own base64 stream (and for zlib data its header and its
/// blocks), as VTK's XML writers encode appended data.
fn appended_base64(set: &ParticleSet, compressed: bool, header64: bool, cut: Streams) -> Vec<u8> {
    use base64::Engine as _;
    let b64 = base64::engine::general_purpose::STANDARD;
    let n = set.len();
    let le = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let flat = |v: &[Vec3]| v.iter().flat_map(|p| p.to_array()).collect::<Vec<f32>>();
    let density: Vec<f32> = set
        .attribute("density")
        .unwrap()
        .values
        .iter()
        .map(|&v| v as f32)
        .collect();
    let phase: Vec<u8> = set
        .attribute("phase")
        .unwrap()
        .values
        .iter()
        .flat_map(|&v| (v as i32).to_le_bytes())
        .collect();
    let ids: Vec<u8> = set
        .ids
        .as_ref()
        .unwrap()
        .iter()
        .flat_map(|i| i.to_le_bytes())
        .collect();
    let arrays: [(&str, &str, usize, Vec<u8>); 5] = [
        ("Points", "Float32", 3, le(&flat(&set.positions))),
        (
            "velocity",
            "Float32",
            3,
            le(&flat(set.velocities.as_ref().unwrap())),
        ),
        ("density", "Float32", 1, le(&density)),
        ("phase", "Int32", 1, phase),
        ("id", "UInt32", 1, ids),
    ];
    let mut text = String::new();
    let mut tags = Vec::new();
    for (name, ty, comps, bytes) in &arrays {
        tags.push(format!(
            "<DataArray type=\"{ty}\" Name=\"{name}\" NumberOfComponents=\"{comps}\" format=\"appended\" offset=\"{}\"/>",
            text.len()
        ));
        if compressed {
            // blocks smaller than the array, so that there are several
            let (header, blocks) = zlib_blocks(bytes, 100, header64);
            text.push_str(&b64.encode(&header));
            match cut {
                Streams::HeaderAndBlocks => text.push_str(&b64.encode(blocks.concat())),
                Streams::EachBlock => {
                    for b in &blocks {
                        text.push_str(&b64.encode(b));
                    }
                }
            }
        } else {
            let size = if header64 {
                (bytes.len() as u64).to_le_bytes().to_vec()
            } else {
                (bytes.len() as u32).to_le_bytes().to_vec()
            };
            text.push_str(&b64.encode(&size));
            text.push_str(&b64.encode(bytes));
        }
    }
    let header_type = if header64 { "UInt64" } else { "UInt32" };
    let compressor = if compressed {
        " compressor=\"vtkZLibDataCompressor\""
    } else {
        ""
    };
    format!(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"{header_type}\"{compressor}>\n<UnstructuredGrid><Piece NumberOfPoints=\"{n}\" NumberOfCells=\"0\">\n<PointData>{}{}{}{}</PointData>\n<Points>{}</Points>\n</Piece></UnstructuredGrid>\n<AppendedData encoding=\"base64\">\n_{text}\n</AppendedData>\n</VTKFile>\n",
        tags[1], tags[2], tags[3], tags[4], tags[0]
    )
    .into_bytes()
}

#[test]
fn appended_base64_reads_per_array_like_raw() {
    // 37 points: sizes that are not multiples of 3, so that every stream ends in `=` padding
    let set = rich_set(37);
    let raw = parse(Format::Vtu, &vtu::to_bytes(&set)).unwrap();
    let mut cases = 0;
    for compressed in [false, true] {
        for header64 in [false, true] {
            for cut in [Streams::HeaderAndBlocks, Streams::EachBlock] {
                if !compressed && matches!(cut, Streams::EachBlock) {
                    continue;
                }
                let bytes = appended_base64(&set, compressed, header64, cut);
                let text = String::from_utf8_lossy(&bytes);
                assert!(
                    text.contains("=="),
                    "the streams are padded inside the section"
                );
                let s = parse(Format::Vtu, &bytes).unwrap_or_else(|e| {
                    panic!("compressed {compressed}, UInt64 {header64}, {cut:?}: {e}")
                });
                assert_eq!(s.positions, raw.positions);
                assert_eq!(s.velocities, raw.velocities);
                assert_eq!(s.ids, raw.ids);
                for name in ["density", "phase"] {
                    assert_eq!(
                        s.attribute(name).unwrap().values,
                        raw.attribute(name).unwrap().values,
                        "{name}"
                    );
                }
                cases += 1;
            }
        }
    }
    assert_eq!(cases, 6);
}

/// Binary legacy VTK files of `set` in three dialects: 3.0 POLYDATA, 4.2 UNSTRUCTURED_GRID (as
/// SPlisHSPlasH writes it) and 5.1 POLYDATA, each with its `POINTS` block's byte range.
fn binary_vtk_dialects(set: &ParticleSet) -> Vec<(&'static str, Vec<u8>, std::ops::Range<usize>)> {
    let v42 = io::to_bytes(Format::Vtk, set, Path::new("x")).unwrap();
    let find =
        |hay: &[u8], needle: &[u8]| hay.windows(needle.len()).position(|w| w == needle).unwrap();
    let points_at = |b: &[u8]| {
        let start = find(b, b"POINTS");
        let data = start + b[start..].iter().position(|&c| c == b'\n').unwrap() + 1;
        data..data + 12 * set.len()
    };
    let cells = find(&v42, b"\nCELLS");
    let point_data = find(&v42, b"POINT_DATA");
    // the text header (up to `POINTS`) in another version and dataset type, the points, then
    // the point data without the cells (poly data of points only)
    let points = find(&v42, b"POINTS");
    let poly = |version: &str| {
        let head = String::from_utf8(v42[..points].to_vec())
            .unwrap()
            .replace("Version 4.2", &format!("Version {version}"))
            .replace("UNSTRUCTURED_GRID", "POLYDATA");
        let mut out = head.into_bytes();
        out.extend_from_slice(&v42[points..cells + 1]);
        out.extend_from_slice(&v42[point_data..]);
        out
    };
    let mut out = Vec::new();
    for (name, bytes) in [
        ("3.0 POLYDATA", poly("3.0")),
        ("4.2", v42.clone()),
        ("5.1 POLYDATA", poly("5.1")),
    ] {
        let head = String::from_utf8_lossy(&bytes[..points_at(&bytes).start]).into_owned();
        let version = &name[..3];
        assert!(
            head.contains(&format!("Version {version}"))
                && head.contains(if name.contains("POLYDATA") {
                    "DATASET POLYDATA"
                } else {
                    "DATASET UNSTRUCTURED_GRID"
                }),
            "{name}: {head}"
        );
        let range = points_at(&bytes);
        out.push((name, bytes, range));
    }
    out
}

#[test]
fn binary_vtk_with_bytes_deleted_or_inserted_in_points_errs_without_panic() {
    let set = rich_set(50);
    for (name, bytes, points) in binary_vtk_dialects(&set) {
        let s = parse(Format::Vtk, &bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(s.positions, set.positions, "{name}");
        let mut errors = 0;
        for at in points.clone() {
            for insert in [false, true] {
                let mut b = bytes.clone();
                if insert {
                    b.insert(at, 0x41);
                } else {
                    b.remove(at);
                }
                let r = std::panic::catch_unwind(|| parse(Format::Vtk, &b));
                let r =
                    r.unwrap_or_else(|_| panic!("{name}: byte {at} (insert {insert}) panicked"));
                errors += r.is_err() as usize;
            }
        }
        // the file cut one byte short of its POINTS block, and at every byte of it
        for end in points.start..=points.end {
            let r = std::panic::catch_unwind(|| parse(Format::Vtk, &bytes[..end - 1]));
            assert!(
                matches!(r, Ok(Err(_))),
                "{name}: cut at {} did not give a clean error",
                end - 1
            );
        }
        println!(
            "{name}: {errors} of {} edits in POINTS refused",
            2 * points.len()
        );
    }
}

/// A VTU file of one zlib-compressed Float32 Points array in raw appended data, `points` points,
/// with the given compression header and blocks.
fn vtu_raw_zlib(points: u64, header: &[u8], blocks: &[u8]) -> Vec<u8> {
    let mut v = format!("<VTKFile type=\"UnstructuredGrid\" compressor=\"vtkZLibDataCompressor\" header_type=\"UInt32\"><UnstructuredGrid><Piece NumberOfPoints=\"{points}\"><Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"appended\" offset=\"0\"/></Points></Piece></UnstructuredGrid><AppendedData encoding=\"raw\">_").into_bytes();
    v.extend_from_slice(header);
    v.extend_from_slice(blocks);
    v.extend_from_slice(b"</AppendedData></VTKFile>");
    v
}

#[test]
fn zlib_headers_and_bombs_are_refused_before_allocating() {
    // a 2.6 kB file whose header claims 4,294,967,295 uncompressed bytes in one block
    let data: Vec<u8> = (0..2400u32)
        .flat_map(|i| (i as f32).to_le_bytes())
        .collect();
    let (mut header, blocks) = zlib_blocks(&data[..], 1 << 16, false);
    header[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
    header[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    let file = vtu_raw_zlib(800, &header, &blocks.concat());
    assert!(file.len() < 4000, "{}", file.len());
    let e = parse(Format::Vtu, &file).unwrap_err();
    assert!(e.to_string().contains("inflates 1032x at most"), "{e}");
    // an honest bomb: the same compressed megabyte of zeros repeated, a point count to match;
    // refused by the budget before inflating
    let mib = vec![0u8; 1 << 20];
    let (one, block) = zlib_blocks(&mib, 1 << 20, false);
    let copies = 40usize;
    let mut header = Vec::new();
    for v in [copies, 1 << 20, 0] {
        header.extend_from_slice(&(v as u32).to_le_bytes());
    }
    for _ in 0..copies {
        header.extend_from_slice(&one[12..16]);
    }
    let file = vtu_raw_zlib(
        (copies as u64 * (1 << 20)) / 12,
        &header,
        &block[0].repeat(copies),
    );
    let small = io::ReadOptions {
        memory_budget: 16 << 20,
    };
    let e = io::parse_bytes_with(Format::Vtu, &file, Path::new("bomb.vtu"), &small).unwrap_err();
    assert!(matches!(e, IoError::OverBudget { .. }), "{e}");
    assert!(e.to_string().contains("--memory-budget"), "{e}");
    // within a budget that holds it, it reads (40 Mi zeros: 3.5 M points at the origin)
    let roomy = io::ReadOptions {
        memory_budget: 64 << 20,
    };
    let s = io::parse_bytes_with(Format::Vtu, &file, Path::new("bomb.vtu"), &roomy).unwrap();
    assert_eq!(s.len(), copies * (1 << 20) / 12);
    // gzipped BGEO: the declared size against the budget too
    let big = rich_set(5000);
    let gz = gzip(
        &io::to_bytes(Format::Bgeo, &big, Path::new("x")).unwrap(),
        flate2::Compression::default(),
    );
    let tiny = io::ReadOptions {
        memory_budget: 64 << 10,
    };
    let e = io::parse_bytes_with(Format::Bgeo, &gz, Path::new("b.bgeo.gz"), &tiny).unwrap_err();
    assert!(matches!(e, IoError::OverBudget { .. }), "{e}");
}

#[test]
fn messages_quote_escape_and_cut_what_the_file_holds() {
    // a terminal escape and a NUL in a VTK keyword line, an 8 kB token in a PLY value
    let text = b"# vtk DataFile Version 3.0\nt\nASCII\nDATASET POLYDATA\n\x1b[31mPOINTS\x00 1 float\n0 0 0\n";
    let e = parse(Format::Vtk, text).unwrap_err().to_string();
    assert!(!e.chars().any(char::is_control), "{e:?}");
    assert!(e.contains("\\u{1b}") && e.contains("\\0"), "{e}");
    let long = format!(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 {}\n",
        "9x".repeat(4000)
    );
    let e = parse(Format::Ply, long.as_bytes()).unwrap_err().to_string();
    assert!(e.len() < 300, "{} characters: {e}", e.len());
    assert!(e.contains("\"9x9x"), "found value quoted: {e}");
}

/// What the fuzz targets found, in `tests/data/fuzz/`: each gives an error a user can read.
/// Three were error messages that escaped control characters from the file at up to eight
/// output characters each, which made them over 300 characters long; one a coordinate that fits
/// an f64 but not an f32, printed in full (256 digits) as the non-finite value (2026-12-02).
#[test]
fn fuzz_findings_read_cleanly() {
    let dir = data("fuzz");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let format = match path.extension().and_then(|e| e.to_str()) {
            Some("vtk") => Format::Vtk,
            Some("vtu") => Format::Vtu,
            Some("bgeo") => Format::Bgeo,
            Some("ply") => Format::Ply,
            Some("xyz") => Format::Xyz,
            Some("json") => Format::Json,
            _ => continue,
        };
        let bytes = std::fs::read(&path).unwrap();
        match io::parse_bytes(format, &bytes, Path::new("fuzz")) {
            Ok(_) => {}
            Err(e) => assert_readable(&e, &path.display().to_string()),
        }
        n += 1;
    }
    assert!(n >= 4, "{n} findings in {}", dir.display());
}
