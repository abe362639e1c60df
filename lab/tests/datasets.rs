//! `.npy`/`.npz` I/O and the dataset readers, against the committed fixtures written by
//! `lab/scripts/make_dataset_fixtures.py` (NumPy, Pillow). No Python runs at test time.
//!
//! `UDAPOSE_BLESS=1 cargo test ...` rewrites `fixtures/npz/rust_written.npz`; then
//! `python lab/scripts/make_dataset_fixtures.py --check-rust` proves `np.load` reads it.

use std::fs;
use std::io::{Cursor, Read, Write};
use std::path::{Path, PathBuf};

use udapose_lab::datasets::nemo::{self, NemoDataset, NemoDirs, NemoFlavor};
use udapose_lab::datasets::syncar::{self, Annotation, SyncarSplit};
use udapose_lab::datasets::{CropFrame, DatasetError, Mask};
use udapose_lab::npz::{NpyArray, NpyData, NpyError, Npz, ReadLimits, npy_bytes, read_npy};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests").join("fixtures")
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-lab-datasets-{}-{name}", std::process::id()));
    fs::create_dir_all(&dir).unwrap();
    dir
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * b.abs().max(1.0)
}

/// Raw bytes of every member of a zip, in archive order.
fn zip_members(bytes: &[u8]) -> Vec<(String, Vec<u8>)> {
    let mut archive = zip::ZipArchive::new(Cursor::new(bytes)).unwrap();
    (0..archive.len())
        .map(|i| {
            let mut member = archive.by_index(i).unwrap();
            let mut data = Vec::new();
            member.read_to_end(&mut data).unwrap();
            (member.name().to_owned(), data)
        })
        .collect()
}

fn data<'a>(npz: &'a Npz, key: &str) -> (&'a [usize], &'a NpyData) {
    let array = npz.get(key).unwrap_or_else(|| panic!("missing {key}"));
    (array.shape(), array.data())
}

// ---------------------------------------------------------------------------------------------
// .npy / .npz reading

const DTYPE_KEYS: [&str; 19] = [
    "f64_scalar",
    "f64_2x3",
    "f32_vec",
    "i64_2x2",
    "i32_vec",
    "i16_vec",
    "i8_vec",
    "u64_vec",
    "u32_vec",
    "u16_vec",
    "u8_2x3",
    "bool_vec",
    "bool_scalar",
    "str_scalar",
    "str_vec",
    "empty_f64",
    "f64_3d",
    "be_f64",
    "none_object",
];

/// Every value the fixture script wrote, checked literally.
fn check_all_dtypes(npz: &Npz) {
    assert_eq!(npz.keys().collect::<Vec<_>>(), DTYPE_KEYS);
    assert_eq!(data(npz, "f64_scalar"), (&[][..], &NpyData::F64(vec![1.25])));
    assert_eq!(data(npz, "f64_2x3"), (&[2, 3][..], &NpyData::F64(vec![-0.5, -0.25, 0.0, 0.25, 0.5, 0.75])));
    assert_eq!(data(npz, "f32_vec"), (&[4][..], &NpyData::F32(vec![1.5, -2.25, 0.125, f32::INFINITY])));
    assert_eq!(data(npz, "i64_2x2"), (&[2, 2][..], &NpyData::I64(vec![-1, 1 << 40, 3, -4])));
    assert_eq!(data(npz, "i32_vec"), (&[3][..], &NpyData::I32(vec![-7, 0, i32::MAX])));
    assert_eq!(data(npz, "i16_vec"), (&[2][..], &NpyData::I16(vec![-300, 300])));
    assert_eq!(data(npz, "i8_vec"), (&[2][..], &NpyData::I8(vec![-128, 127])));
    assert_eq!(data(npz, "u64_vec"), (&[2][..], &NpyData::U64(vec![0, u64::MAX])));
    assert_eq!(data(npz, "u32_vec"), (&[1][..], &NpyData::U32(vec![u32::MAX])));
    assert_eq!(data(npz, "u16_vec"), (&[2][..], &NpyData::U16(vec![65535, 1])));
    assert_eq!(data(npz, "u8_2x3"), (&[2, 3][..], &NpyData::U8(vec![0, 1, 255, 7, 8, 9])));
    assert_eq!(data(npz, "bool_vec"), (&[5][..], &NpyData::Bool(vec![true, false, true, true, false])));
    assert_eq!(data(npz, "bool_scalar"), (&[][..], &NpyData::Bool(vec![true])));
    assert_eq!(data(npz, "str_scalar"), (&[][..], &NpyData::Str(vec!["n02814533_1234".into()])));
    let strings = NpyData::Str(vec!["café".into(), "ü🚗".into(), "a".into()]);
    assert_eq!(data(npz, "str_vec"), (&[3][..], &strings));
    assert_eq!(data(npz, "empty_f64"), (&[0][..], &NpyData::F64(vec![])));
    assert_eq!(data(npz, "f64_3d"), (&[2, 1, 3][..], &NpyData::F64(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0])));
    assert_eq!(data(npz, "be_f64"), (&[2][..], &NpyData::F64(vec![1.0, -2.0])));
    let (shape, object) = data(npz, "none_object");
    assert!(shape.is_empty() && matches!(object, NpyData::Object(pickle) if !pickle.is_empty()));
}

#[test]
fn reads_every_dtype_from_stored_and_deflated_npz() {
    check_all_dtypes(&Npz::read_path(fixtures().join("npz/dtypes.npz")).unwrap());
    check_all_dtypes(&Npz::read_path(fixtures().join("npz/dtypes_compressed.npz")).unwrap());
}

#[test]
fn typed_getters_convert_like_python() {
    let npz = Npz::read_path(fixtures().join("npz/dtypes.npz")).unwrap();
    assert_eq!(npz.f64_scalar("f64_scalar").unwrap(), 1.25);
    assert_eq!(npz.f64_scalar("u32_vec").unwrap(), f64::from(u32::MAX));
    assert_eq!(npz.i64_scalar("bool_scalar").unwrap(), 1);
    assert_eq!(npz.str_scalar("str_scalar").unwrap(), "n02814533_1234");
    assert_eq!(npz.f64_array("i8_vec").unwrap(), (vec![2], vec![-128.0, 127.0]));
    assert_eq!(npz.u8_array("bool_vec").unwrap(), (vec![5], vec![1, 0, 1, 1, 0]));
    assert_eq!(npz.u8_array("u16_vec").ok(), None, "65535 does not fit a u8");
    assert!(matches!(npz.i64_scalar("f64_scalar"), Err(NpyError::WrongType { .. })), "1.25 is not integral");
    assert!(matches!(npz.f64_scalar("f64_2x3"), Err(NpyError::WrongType { .. })), "6 elements");
    assert!(matches!(npz.str_scalar("f64_scalar"), Err(NpyError::WrongType { .. })));
    assert!(matches!(npz.f64_array("none_object"), Err(NpyError::WrongType { .. })));
    assert!(matches!(npz.f64_scalar("nope"), Err(NpyError::MissingKey(k)) if k == "nope"));
    assert_eq!(npz.get("u64_vec").unwrap().to_i64_vec(), None, "u64::MAX does not fit an i64");
}

#[test]
fn reads_npy_versions_2_and_3_and_rejects_fortran_order() {
    let expected = NpyArray::new(vec![2, 3], NpyData::I32(vec![0, 1, 2, 3, 4, 5])).unwrap();
    for file in ["v2.npy", "v3.npy"] {
        let bytes = fs::read(fixtures().join("npz").join(file)).unwrap();
        assert_eq!(bytes[6], if file == "v2.npy" { 2 } else { 3 });
        assert_eq!(read_npy(&bytes).unwrap(), expected, "{file}");
    }
    let fortran = fs::read(fixtures().join("npz/fortran.npy")).unwrap();
    assert!(matches!(read_npy(&fortran), Err(NpyError::FortranOrder(shape)) if shape == [2, 3]));
}

// ---------------------------------------------------------------------------------------------
// .npy / .npz writing

#[test]
fn npy_members_are_byte_identical_to_numpy() {
    let bytes = fs::read(fixtures().join("npz/dtypes.npz")).unwrap();
    let npz = Npz::from_bytes(&bytes).unwrap();
    for (name, raw) in zip_members(&bytes) {
        let key = name.strip_suffix(".npy").unwrap();
        if key == "be_f64" {
            continue; // the value model keeps values, not byte order: rewritten as '<f8'
        }
        assert_eq!(npy_bytes(npz.get(key).unwrap()), raw, "{key}");
    }
}

#[test]
fn npz_writes_are_deterministic_round_trip_and_match_the_python_checked_file() {
    let npz = Npz::read_path(fixtures().join("npz/dtypes.npz")).unwrap();
    let first = npz.to_bytes().unwrap();
    assert_eq!(first, npz.to_bytes().unwrap());
    let back = Npz::from_bytes(&first).unwrap();
    assert_eq!(back, npz);
    check_all_dtypes(&back);
    // Stored members in the given order, each starting its data 64-byte aligned.
    for (key, (name, raw)) in npz.keys().zip(zip_members(&first)) {
        assert_eq!(name, format!("{key}.npy"));
        let header_len = usize::from(u16::from_le_bytes([raw[8], raw[9]]));
        assert_eq!((10 + header_len) % 64, 0, "{key}");
    }
    let golden = fixtures().join("npz/rust_written.npz");
    if std::env::var_os("UDAPOSE_BLESS").is_some() {
        // A blessing run never passes: the new file is checked by NumPy, then by a plain run.
        fs::write(&golden, &first).unwrap();
        panic!(
            "wrote {}; check it with `make_dataset_fixtures.py --check-rust`, then rerun without UDAPOSE_BLESS",
            golden.display()
        );
    }
    // The same bytes as the file `make_dataset_fixtures.py --check-rust` loaded with np.load.
    assert_eq!(first, fs::read(&golden).unwrap(), "rerun with UDAPOSE_BLESS=1 and --check-rust");
}

#[test]
fn write_path_is_atomic_and_readable() {
    let dir = scratch("write-path");
    let path = dir.join("a.npz");
    let mut npz = Npz::new();
    npz.insert("x", 2.5);
    npz.insert("name", "car");
    npz.insert("x", 3.5); // replaces in place
    npz.write_path(&path).unwrap();
    assert!(!dir.join("a.npz.tmp").exists());
    let back = Npz::read_path(&path).unwrap();
    assert_eq!(back.keys().collect::<Vec<_>>(), ["x", "name"]);
    assert_eq!(back.f64_scalar("x").unwrap(), 3.5);
    fs::remove_dir_all(dir).unwrap();
}

#[test]
fn array_constructor_checks_the_shape() {
    let err = NpyArray::new(vec![2, 2], NpyData::F64(vec![1.0; 3])).unwrap_err();
    assert!(matches!(err, NpyError::ShapeMismatch { expected: 4, actual: 3, .. }));
    assert!(NpyArray::new(vec![usize::MAX, 2], NpyData::U8(vec![])).is_err());
    let empty_string = NpyArray::from("");
    assert!(npy_bytes(&empty_string).windows(5).any(|w| w == b"'<U1'"), "np.array('') is <U1");
}

// ---------------------------------------------------------------------------------------------
// Malformed input: typed errors, no panic, no allocation from a lying header

/// A version-1.0 `.npy` with `dict` as its header (padded like NumPy) and `data` after it.
fn npy_with_header(dict: &str, data: &[u8]) -> Vec<u8> {
    let mut header = dict.to_owned();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

#[test]
fn malformed_npy_gives_typed_errors() {
    let header =
        |descr: &str, shape: &str| format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    assert!(matches!(read_npy(b"PK\x03\x04 not numpy"), Err(NpyError::BadMagic)));
    assert!(matches!(read_npy(b"\x93NUM"), Err(NpyError::Truncated { .. })));
    assert!(matches!(read_npy(b"\x93NUMPY\x04\x00\x10\x00"), Err(NpyError::UnsupportedVersion(4, 0))));
    let mut cut = npy_with_header(&header("<f8", "(2,)"), &[0; 16]);
    cut.truncate(40);
    assert!(matches!(read_npy(&cut), Err(NpyError::Truncated { .. })), "header cut short");
    // A header claiming 10^12 doubles over 16 bytes of data: refused before any allocation.
    let huge = npy_with_header(&header("<f8", "(1000000, 1000000)"), &[0; 16]);
    assert!(matches!(read_npy(&huge), Err(NpyError::Truncated { needed: 8_000_000_000_000, available: 16 })));
    let overflow = npy_with_header(&header("<f8", "(18446744073709551615, 4)"), &[]);
    assert!(matches!(read_npy(&overflow), Err(NpyError::BadHeader(_))));
    for descr in ["<c16", "<U0", "|V8", "<M8[ns]"] {
        let bytes = npy_with_header(&header(descr, "(1,)"), &[0; 16]);
        assert!(matches!(read_npy(&bytes), Err(NpyError::UnsupportedDtype(_))), "{descr}");
    }
    let structured = npy_with_header("{'descr': [('a', '<f8')], 'fortran_order': False, 'shape': (1,), }", &[0; 8]);
    assert!(matches!(read_npy(&structured), Err(NpyError::UnsupportedDtype(_))));
    for bad in [
        "{'descr': '<f8', 'shape': (1,), }",
        "{'descr': '<f8' 'fortran_order': False}",
        "not a dict",
        "{'descr': '<f8', 'fortran_order': 1, 'shape': (1,)}",
    ] {
        assert!(matches!(read_npy(&npy_with_header(bad, &[0; 8])), Err(NpyError::BadHeader(_))), "{bad}");
    }
    let surrogate = npy_with_header(&header("<U1", "(1,)"), &0xD800u32.to_le_bytes());
    assert!(matches!(read_npy(&surrogate), Err(NpyError::BadString(0xD800))));
    let mut long_header = b"\x93NUMPY\x02\x00".to_vec();
    long_header.extend_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(read_npy(&long_header), Err(NpyError::TooLarge { .. })));
}

fn zip_with(members: &[(&str, &[u8])], method: zip::CompressionMethod) -> Vec<u8> {
    let mut writer = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default().compression_method(method);
    for (name, data) in members {
        writer.start_file(*name, options).unwrap();
        writer.write_all(data).unwrap();
    }
    writer.finish().unwrap().into_inner()
}

#[test]
fn malformed_npz_gives_typed_errors() {
    let good = fs::read(fixtures().join("npz/dtypes.npz")).unwrap();
    assert!(matches!(Npz::from_bytes(&good[..good.len() / 2]), Err(NpyError::Zip(_))), "truncated zip");
    assert!(matches!(Npz::from_bytes(b"\x93NUMPY not a zip"), Err(NpyError::Zip(_))));
    assert!(matches!(Npz::from_bytes(&[]), Err(NpyError::Zip(_))));

    let stored = zip::CompressionMethod::Stored;
    let readme = zip_with(&[("readme.txt", b"hello")], stored);
    assert!(matches!(Npz::from_bytes(&readme), Err(NpyError::NotNpy(name)) if name == "readme.txt"));
    let member = npy_bytes(&NpyArray::from(1.0));
    let bad_member = zip_with(&[("a.npy", &member), ("b.npy", b"garbage")], stored);
    let err = Npz::from_bytes(&bad_member).unwrap_err();
    assert!(matches!(&err, NpyError::Entry { key, source } if key == "b" && matches!(**source, NpyError::BadMagic)));

    // A deflate "bomb": 4 MiB of zeros in a few KiB, read under a 1 MiB cap.
    let zeros = npy_bytes(&NpyArray::from(vec![0u8; 4 << 20]));
    let bomb = zip_with(&[("z.npy", &zeros)], zip::CompressionMethod::Deflated);
    assert!(bomb.len() < 64 << 10);
    let limits = ReadLimits { max_entry_bytes: 1 << 20, ..ReadLimits::default() };
    let err = Npz::read_from(Cursor::new(&bomb), &limits).unwrap_err();
    assert!(matches!(err, NpyError::TooLarge { .. }), "{err}");
    assert!(Npz::read_from(Cursor::new(&bomb), &ReadLimits::default()).is_ok());
    let few = ReadLimits { max_entries: 3, ..ReadLimits::default() };
    assert!(matches!(Npz::read_from(Cursor::new(&good), &few), Err(NpyError::TooLarge { .. })));

    // Corrupting a stored member's data (the UTF-32 'n' of "n02814533_1234") is caught by the CRC.
    let mut corrupt = good.clone();
    let pos = corrupt.windows(8).position(|w| w == b"n\0\0\x000\0\0\0").unwrap();
    corrupt[pos] = b'm';
    assert!(matches!(Npz::from_bytes(&corrupt), Err(NpyError::Io(_))));
}

// ---------------------------------------------------------------------------------------------
// SynCar-OOD

fn syncar_root() -> PathBuf {
    fixtures().join("syncar")
}

fn expected_mask(offset: usize) -> Mask {
    let mut data = vec![0u8; 8 * 20];
    for row in 2..6 {
        for col in 3 + offset..15 + offset {
            data[row * 20 + col] = 1;
        }
    }
    Mask::new(8, 20, data).unwrap()
}

#[test]
fn syncar_split_lists_and_loads_every_value() {
    let split = SyncarSplit::open(&syncar_root(), "source", "test").unwrap();
    let names: Vec<_> = split.entries().iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names, ["000000.png", "000001.png"]);
    let base = syncar_root().join("source/test");
    assert_eq!(split.entries()[1].image_path, base.join("images/car/000001.png"));
    assert_eq!(split.entries()[1].annotation_path, base.join("annotations/car/000001.npz"));

    let samples: Vec<_> = split.iter().collect::<Result<_, _>>().unwrap();
    let expected = [(0.5, 0.25, -0.125, 6.5, 0.875, "p406", 11), (3.0, -0.1, 0.05, 9.75, 0.8125, "155-DTM", 1)];
    for (i, (sample, (az, el, th, d, fill, car, cad))) in samples.iter().zip(expected).enumerate() {
        assert_eq!(sample.frame, CropFrame::Native);
        let a = &sample.annotation;
        let p = a.pose;
        assert_eq!((p.azimuth, p.elevation, p.theta, p.distance), (az, el, th, d));
        assert_eq!((p.principal, p.viewport, p.focal, p.height, p.width), ([10.0, 4.0], 93.75, 1.0, 8, 20));
        assert_eq!((a.fill, a.car.as_str(), a.cad_index, a.occ_fraction), (fill, car, cad, None));
        assert_eq!(a.mask, expected_mask(i));
        assert_eq!(a.mask.count(), 48);
        let (w, h) = image::image_dimensions(&sample.entry.image_path).unwrap();
        assert_eq!((h as usize, w as usize), (p.height, p.width));
        let camera = p.camera().unwrap();
        assert_eq!((camera.viewport, camera.principal, camera.width, camera.height), (93.75, [10.0, 4.0], 20, 8));
        assert_eq!(p.pose().distance, d);
    }
    assert!(matches!(split.load(2), Err(DatasetError::Invalid { .. })));
}

#[test]
fn syncar_occlusion_domain_has_occ_fraction() {
    let split = SyncarSplit::open(&syncar_root(), "occ-l1", "test").unwrap();
    assert_eq!(split.len(), 1);
    let a = split.load(0).unwrap().annotation;
    assert_eq!((a.pose.azimuth, a.pose.elevation, a.pose.theta, a.pose.distance), (1.5, 0.5, 0.0, 4.25));
    assert_eq!((a.fill, a.car.as_str(), a.cad_index, a.occ_fraction), (0.9, "car1-ow1", 15, Some(0.3125)));
    assert_eq!(a.mask, expected_mask(0));
}

#[test]
fn syncar_writer_matches_numpy_member_for_member_and_is_deterministic() {
    let dir = scratch("syncar-writer");
    for (domain, name) in [("source", "000000"), ("source", "000001"), ("occ-l1", "000000")] {
        let python_path = syncar_root().join(domain).join("test/annotations/car").join(format!("{name}.npz"));
        let annotation = syncar::read_syncar_annotation(&python_path).unwrap();
        let rust_path = dir.join(format!("{domain}-{name}.npz"));
        syncar::write_syncar_annotation(&rust_path, &annotation).unwrap();
        let rust_bytes = fs::read(&rust_path).unwrap();
        // Same keys, same order, and every .npy member byte-identical to np.savez's.
        let ours = zip_members(&rust_bytes);
        let theirs = zip_members(&fs::read(&python_path).unwrap());
        assert_eq!(ours, theirs, "{domain}/{name}");
        let key_order: Vec<_> = ours.iter().map(|(n, _)| n.trim_end_matches(".npy").to_owned()).collect();
        let documented = syncar::KEYS.iter().filter(|k| match **k {
            "occ_fraction" => annotation.occ_fraction.is_some(),
            "occluder" => annotation.occluder.is_some(),
            _ => true,
        });
        assert_eq!(key_order, documented.map(|k| k.to_string()).collect::<Vec<_>>());
        // Round trip and byte-identical rewrites.
        assert_eq!(syncar::read_syncar_annotation(&rust_path).unwrap(), annotation);
        syncar::write_syncar_annotation(&rust_path, &annotation).unwrap();
        assert_eq!(fs::read(&rust_path).unwrap(), rust_bytes);
    }
    fs::remove_dir_all(dir).unwrap();
}

#[test]
fn syncar_split_written_by_rust_reads_back() {
    let source = SyncarSplit::open(&syncar_root(), "source", "test").unwrap();
    let root = scratch("syncar-split");
    let paths = syncar::SplitPaths::new(&root, "corrupt/fog", "adapt");
    fs::create_dir_all(&paths.annotations).unwrap();
    fs::create_dir_all(paths.list.parent().unwrap()).unwrap();
    let names: Vec<String> = source.entries().iter().map(|e| e.name.clone()).collect();
    syncar::write_syncar_list(&paths.list, &names).unwrap();
    assert_eq!(fs::read_to_string(&paths.list).unwrap(), "000000.png\n000001.png\n");
    for sample in source.iter() {
        let sample = sample.unwrap();
        let path = paths.annotations.join(sample.entry.annotation_path.file_name().unwrap());
        syncar::write_syncar_annotation(&path, &sample.annotation).unwrap();
    }
    let copy = SyncarSplit::open(&root, "corrupt/fog", "adapt").unwrap();
    assert_eq!(copy.paths(), &paths);
    for (a, b) in source.iter().zip(copy.iter()) {
        let (a, b) = (a.unwrap(), b.unwrap());
        assert_eq!((&a.entry.name, &a.annotation), (&b.entry.name, &b.annotation));
    }
    fs::remove_dir_all(root).unwrap();
}

#[test]
fn syncar_writer_rejects_a_mask_of_the_wrong_size() {
    let path = fixtures().join("syncar/source/test/annotations/car/000000.npz");
    let mut annotation: Annotation = syncar::read_syncar_annotation(&path).unwrap();
    annotation.mask = Mask::new(20, 8, vec![0; 160]).unwrap(); // transposed
    let dir = scratch("syncar-bad-mask");
    let out = dir.join("bad.npz");
    assert!(matches!(syncar::write_syncar_annotation(&out, &annotation), Err(DatasetError::Npz { .. })));
    assert!(!out.exists());
    fs::remove_dir_all(dir).unwrap();
}

#[test]
fn syncar_reader_reports_missing_files() {
    assert!(matches!(SyncarSplit::open(&syncar_root(), "fog", "test"), Err(DatasetError::Io { .. })));
    let bad = syncar::read_syncar_annotation(&fixtures().join("npz/dtypes.npz")).unwrap_err();
    assert!(matches!(bad, DatasetError::Npz { source: NpyError::MissingKey(_), .. }), "{bad}");
}

// ---------------------------------------------------------------------------------------------
// NeMo exports

const CROP: (usize, usize) = (16, 42);

#[test]
fn nemo_pascal3d_union_of_lists_and_crop_frame() {
    let root = fixtures().join("nemo_pascal3d");
    let dataset = NemoDataset::open(&root, "car").unwrap();
    let names: Vec<_> = dataset.entries().iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names, ["n02814533_101", "n02814533_202", "n02814533_303"], "deduplicated, sorted, no .JPEG");
    assert_eq!(dataset.entries()[0].image_path, root.join("images/car/n02814533_101.JPEG"));

    let samples: Vec<_> = dataset.iter().collect::<Result<_, _>>().unwrap();
    let expected: [(f64, f64, f64, f64, [f64; 2], i64); 3] = [
        (30.0, 10.0, -2.0, 5.6, [31.5, 23.25], 3),
        (200.0, 5.0, 4.0, 4.0, [3.5, 40.75], 1),
        (350.0, 20.0, 0.0, 7.5, [40.25, 20.5], 3),
    ];
    for (s, (az, el, th, d, principal, cad)) in samples.iter().zip(expected) {
        assert_eq!((s.frame, s.flavor), (CropFrame::NemoNormalised, NemoFlavor::Original));
        let p = s.pose;
        assert!(close(p.azimuth, az * std::f64::consts::PI / 180.0) && close(p.elevation, el.to_radians()));
        assert!(close(p.theta, th.to_radians()));
        assert_eq!((p.distance, p.principal, p.viewport, p.focal), (5.0, [21.0, 8.0], 3000.0, 1.0));
        assert_eq!((p.height, p.width), CROP);
        assert_eq!(s.original_distance, d);
        let a = &s.annotation;
        assert_eq!((a.distance, a.principal, a.cad_index, a.height, a.width), (d, principal, cad, 48, 64));
        assert_eq!(a.name, s.entry.name);
        assert_eq!((a.occ_mask.as_ref(), a.resize_rate, a.nuisance.as_deref()), (None, None, None));
        assert_eq!(a.cropped_kp_list.as_deref(), Some(&[[4.5, 10.25], [0.0, 0.0], [9.0, 30.5]][..]));
        let (w, h) = image::image_dimensions(&s.entry.image_path).unwrap();
        assert_eq!((h as usize, w as usize), CROP, "the JPEG is the crop");
    }
    // MATLAB-double keypoint states (first sample) and int ones (second) both map to visibility.
    assert_eq!(samples[0].annotation.visible.as_deref(), Some(&[true, false, true][..]));
    assert_eq!(samples[1].annotation.visible.as_deref(), Some(&[true, true, false][..]));
    let a = &samples[1].annotation;
    assert_eq!(a.bbox, Some([0.0, 30.0, 10.0, 48.0]));
    let b = a.crop_box.unwrap();
    assert_eq!((b.y0, b.y1, b.x0, b.x1, b.boundary), (24.0, 40.0, 0.0, 42.0, Some([40.0, 70.0])));
    let b = a.box_ori.unwrap();
    assert_eq!((b.y0, b.y1, b.x0, b.x1, b.boundary), (30.0, 48.0, 0.0, 10.0, Some([48.0, 64.0])));
    let b = a.box_obj.unwrap();
    assert_eq!((b.y0, b.y1, b.x0, b.x1, b.boundary), (0.0, 14.0, 19.0, 27.0, Some([16.0, 42.0])));
    assert_eq!(a.crop_size(), Some(CROP));
}

#[test]
fn nemo_occluded_pascal3d_keeps_the_original_image_occluder_mask() {
    let root = fixtures().join("nemo_pascal3d");
    let dataset = NemoDataset::open(&root, &nemo::occluded_category("car", 1)).unwrap();
    assert_eq!(dataset.len(), 1);
    let s = dataset.load(0).unwrap();
    assert_eq!(s.entry.image_path, root.join("images/carFGL1_BGL1/n02814533_101.JPEG"));
    let occ = s.annotation.occ_mask.as_ref().unwrap();
    assert_eq!((occ.height, occ.width, occ.count()), (48, 64, 200));
    assert_eq!((occ.get(20, 5), occ.get(19, 5), occ.get(48, 0)), (Some(1), Some(0), None));
    assert_eq!(s.occ_mask_in_crop(), None, "Angtian/NeMo stores the original image's mask");
    assert_eq!(s.annotation.visible.as_deref(), Some(&[false][..]));
    assert_eq!((s.pose.distance, s.original_distance), (5.0, 5.6));
}

#[test]
fn nemo_oodcv_reads_nuisance_resize_rate_and_unsuffixed_lists() {
    let dataset = NemoDataset::open(&fixtures().join("nemo_oodcv/val"), "car").unwrap();
    let names: Vec<_> = dataset.entries().iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names, ["n02814533_101_00", "n02814533_202_00"]);
    let s: Vec<_> = dataset.iter().collect::<Result<_, _>>().unwrap();
    for (sample, (nuisance, rate, d)) in s.iter().zip([("weather", 5.6 / 5.0, 5.6), ("iid", 4.0 / 5.0, 4.0)]) {
        let a = &sample.annotation;
        assert_eq!(sample.flavor, NemoFlavor::OodCvPose);
        assert_eq!((a.nuisance.as_deref(), a.resize_rate, a.distance), (Some(nuisance), Some(rate), d));
        assert!(close(sample.pose.distance, 5.0), "{}", sample.pose.distance);
        assert_eq!((sample.pose.principal, sample.original_distance), ([21.0, 8.0], d));
        assert_eq!(a.name, sample.entry.name.trim_end_matches("_00"));
        assert_eq!((a.height, a.width, a.cropped_kp_list.as_ref(), a.occ_mask.as_ref()), (48, 64, None, None));
    }
    assert_eq!(s[1].annotation.padding_params.as_deref(), Some(&[0, 2, 19, 0, 0, 0][..]));
}

#[test]
fn nemo_neural_mesh_model_export_is_already_in_the_crop() {
    let dataset = NemoDataset::open(&fixtures().join("nemo_nmm/val"), "car").unwrap();
    let s = dataset.load(0).unwrap();
    assert_eq!(s.flavor, NemoFlavor::NeuralMeshModel);
    assert_eq!((s.pose.distance, s.pose.principal, s.original_distance), (5.0, [21.0, 8.0], 7.5));
    let a = &s.annotation;
    assert_eq!((a.crop_principal, a.cad_index, a.true_cad_index), (Some([21.0, 8.0]), 3, Some(3)));
    assert_eq!(a.kp_weights.as_deref(), Some(&[0.5, 1.0][..]));
    assert_eq!(a.cropped_kp_list.as_deref(), Some(&[[3.0, 4.0], [5.0, 6.0]][..]));
    assert_eq!(a.visible.as_deref(), Some(&[true, false][..]));
    assert!(close(s.pose.azimuth, 350f64.to_radians()) && close(s.pose.elevation, 20f64.to_radians()));
}

#[test]
fn nemo_reader_reports_bad_layouts() {
    let root = fixtures().join("nemo_pascal3d");
    assert!(matches!(NemoDataset::open(&root, "bus"), Err(DatasetError::Io { .. })));
    let dirs = NemoDirs::three_d("single");
    assert_eq!(dirs.lists, "lists3D_single");
    assert!(matches!(NemoDataset::open_with(&root, "car", &dirs), Err(DatasetError::Io { .. })));
    let empty = scratch("nemo-empty");
    fs::create_dir_all(empty.join("lists/car")).unwrap();
    assert!(matches!(NemoDataset::open(&empty, "car"), Err(DatasetError::Invalid { .. })));
    fs::remove_dir_all(empty).unwrap();
}
