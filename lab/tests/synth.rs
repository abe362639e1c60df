//! The `quick` SynCar-OOD dataset: every domain and split with its counts, annotations in their
//! ranges, occlusion inside its bands, and byte-identical regeneration from the same seed.
//!
//! `make test` renders the dataset once per run and passes it in `UDAPOSE_QUICK_DATA`; without
//! it this test renders its own copy (about 3 minutes on 2 cores).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use udapose_lab::assets::{SHAPE_CARS, SOURCE_CARS};
use udapose_lab::datasets::syncar::{SplitPaths, read_syncar_annotation};
use udapose_lab::synth::{Profile, all_domains};

const LAB: &str = env!("CARGO_BIN_EXE_udapose-lab");

fn synth(out: &Path, domains: &[&str]) {
    let mut cmd = Command::new(LAB);
    cmd.args(["synth", "--profile", "quick", "--seed", "0", "--out"]).arg(out);
    if !domains.is_empty() {
        cmd.arg("--domains").arg(domains.join(","));
    }
    let status = cmd.status().expect("run udapose-lab synth");
    assert!(status.success(), "udapose-lab synth failed: {status}");
}

fn dataset() -> &'static Path {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| match std::env::var_os("UDAPOSE_QUICK_DATA") {
        Some(dir) => PathBuf::from(dir),
        None => {
            let dir = std::env::temp_dir().join(format!("udapose-quick-{}", std::process::id()));
            synth(&dir, &[]);
            dir
        }
    })
}

#[test]
fn every_domain_and_split_has_its_images() {
    let root = dataset();
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["profile"], "quick");
    let domains = all_domains();
    assert_eq!(domains.len(), 1 + 6 + 19 + 4, "source, 6 nuisance domains, 19 corruptions, 4 occlusion");
    for d in &domains {
        for split in d.splits {
            let n = Profile::Quick.count(split);
            let paths = SplitPaths::new(root, &d.name, split);
            let list = std::fs::read_to_string(&paths.list).unwrap_or_else(|e| panic!("{}: {e}", paths.list.display()));
            let names: Vec<&str> = list.lines().collect();
            assert_eq!(names.len(), n, "{}/{split}", d.name);
            assert_eq!(manifest["counts"][&d.name][split], n);
            for name in names {
                let img = image::open(paths.images.join(name)).unwrap();
                assert_eq!((img.width(), img.height()), (160, 64));
                assert!(paths.annotations.join(name.replace(".png", ".npz")).is_file());
            }
        }
    }
    assert_eq!(Profile::Quick.count("train"), 300);
    assert_eq!(Profile::Quick.count("val"), 60);
}

#[test]
fn annotations_lie_in_their_ranges() {
    let root = dataset();
    let deg = f64::to_radians;
    let mut occ: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for d in all_domains() {
        for split in d.splits {
            let paths = SplitPaths::new(root, &d.name, split);
            for i in 0..Profile::Quick.count(split) {
                let a = read_syncar_annotation(&paths.annotations.join(format!("{i:05}.npz"))).unwrap();
                let p = &a.pose;
                let at = format!("{}/{split}/{i}", d.name);
                assert!((0.0..std::f64::consts::TAU).contains(&p.azimuth), "{at}");
                // Combined domains may draw the pose nuisance, so they allow either range.
                let pose_shift = d.name == "pose";
                let any = d.name == "combined" || d.name.starts_with("occ") || d.name.starts_with("extreme");
                let (el, th) = if pose_shift { ((30.0, 70.0), 40.0) } else { ((-10.0, 40.0), 15.0) };
                let (el, th) = if any { ((-10.0, 70.0), 40.0) } else { (el, th) };
                assert!(p.elevation >= deg(el.0) - 1e-12 && p.elevation <= deg(el.1) + 1e-12, "{at}: {}", p.elevation);
                assert!(p.theta.abs() <= deg(th) + 1e-12, "{at}: theta {}", p.theta);
                assert!((0.80..0.95).contains(&a.fill), "{at}: fill {}", a.fill);
                assert!(p.distance > 1.5 && p.distance < 25.0, "{at}: distance {}", p.distance);
                assert_eq!((p.principal, p.viewport, p.focal, p.height, p.width), ([80.0, 32.0], 750.0, 1.0, 64, 160));
                let cars: Vec<&str> = if d.name == "shape" {
                    SHAPE_CARS.to_vec()
                } else if any {
                    [SOURCE_CARS.as_slice(), &SHAPE_CARS].concat()
                } else {
                    SOURCE_CARS.to_vec()
                };
                assert!(cars.contains(&a.car.as_str()), "{at}: car {}", a.car);
                let all_cars: Vec<&str> = [SOURCE_CARS.as_slice(), &SHAPE_CARS].concat();
                assert_eq!(all_cars[a.cad_index as usize], a.car);
                let covered = a.mask.data.iter().filter(|&&m| m == 1).count();
                assert!(covered > 200 && a.mask.data.iter().all(|&m| m <= 1), "{at}: mask of {covered} pixels");
                match (d.occlusion, a.occ_fraction) {
                    (Some(band), Some(f)) => {
                        assert!(f >= band.0 && f <= band.1, "{at}: occlusion {f} outside {band:?}");
                        // The stored occluder mask covers exactly that share of the object.
                        let o = a.occluder.as_ref().unwrap_or_else(|| panic!("{at}: no occluder mask"));
                        let hidden = o.data.iter().zip(&a.mask.data).filter(|&(&o, &m)| o == 1 && m == 1).count();
                        assert_eq!(hidden as f64 / covered as f64, f, "{at}");
                        occ.entry(d.name.clone()).or_default().push(f);
                    }
                    (None, None) => assert!(a.occluder.is_none(), "{at}: an occluder without occlusion"),
                    other => panic!("{at}: occlusion {other:?}"),
                }
            }
        }
    }
    assert_eq!(occ.len(), 4, "occ-l1, occ-l2, occ-l3 and extreme-l2 store their fractions");
}

#[test]
fn the_same_seed_gives_identical_files() {
    let root = dataset();
    let again = std::env::temp_dir().join(format!("udapose-quick-again-{}", std::process::id()));
    let domains = ["shape", "weather", "occ-l2", "corrupt/glass_blur", "corrupt/frost"];
    synth(&again, &domains);
    for d in domains {
        for split in ["adapt", "test"] {
            let (a, b) = (SplitPaths::new(root, d, split), SplitPaths::new(&again, d, split));
            assert_eq!(std::fs::read(&a.list).unwrap(), std::fs::read(&b.list).unwrap());
            for i in 0..Profile::Quick.count(split) {
                for (x, y, ext) in [(&a.images, &b.images, "png"), (&a.annotations, &b.annotations, "npz")] {
                    let name = format!("{i:05}.{ext}");
                    assert!(
                        std::fs::read(x.join(&name)).unwrap() == std::fs::read(y.join(&name)).unwrap(),
                        "{d}/{split}/{name} differs"
                    );
                }
            }
        }
    }
    std::fs::remove_dir_all(&again).unwrap();
}

#[test]
fn the_car_cuboid_is_fixed() {
    // METHOD.md §3: 99% extent of the pooled source-car vertices, wheels included.
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dataset().join("manifest.json")).unwrap()).unwrap();
    let corner = |k: &str| -> [f64; 3] { std::array::from_fn(|a| manifest["cuboid"][k][a].as_f64().unwrap()) };
    let cuboid = udapose_engine::Cuboid { min: corner("min"), max: corner("max") };
    let dims_mm = cuboid.dimensions().map(|d| d * 1000.0);
    for (got, want) in dims_mm.iter().zip([434.2, 989.1, 278.6]) {
        assert!((got - want).abs() < 0.5, "cuboid {dims_mm:?} mm per unit length");
    }
    assert_eq!(cuboid.mesh(udapose_engine::mesh::TARGET_VERTICES).vertices().len(), 1054);
}
