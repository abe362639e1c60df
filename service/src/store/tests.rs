//! The store on a local directory and on an in-memory object store.

use super::*;

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-store-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    dir
}

fn shipped() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/car")
}

#[test]
fn a_remote_store_keeps_only_the_last_used_downloads() {
    let cache = temp("cache");
    let objects = Arc::new(object_store::memory::InMemory::new());
    let store = Store::with_objects(objects, None, &cache, "memory://").unwrap();
    // Tiny versions: the shipped manifest listing one small file.
    let mut manifest: serde_json::Value = serde_json::from_slice(&fs::read(shipped().join(MANIFEST)).unwrap()).unwrap();
    manifest["files"] = serde_json::json!({ "w.bin": sha256_hex(b"w") });
    for v in ["v1", "v2", "v3", "v4", "v5"] {
        let prefix = format!("models/car/versions/{v}");
        store.create(&format!("{prefix}/w.bin"), b"w".to_vec()).unwrap();
        store.create(&format!("{prefix}/{MANIFEST}"), serde_json::to_vec(&manifest).unwrap()).unwrap();
    }
    let hours_ago = |h: u64| SystemTime::now() - Duration::from_secs(3600 * h);
    let car = cache.join("udapose-versions/car");
    let cached = || ["v1", "v2", "v3", "v4", "v5"].map(|v| car.join(v).is_dir());
    for (v, h) in [("v1", 5), ("v2", 4), ("v3", 3)] {
        store.version_dir("car", v).unwrap();
        fs::File::open(car.join(v)).unwrap().set_modified(hours_ago(h)).unwrap();
    }
    // A cache hit marks v1 as used now, so v2 is the least recently used when v4 comes in.
    store.version_dir("car", "v1").unwrap();
    store.version_dir("car", "v4").unwrap();
    assert_eq!(cached(), [true, false, true, true, false]);
    // A crashed download's temporary directory goes too, once as old as the grace period.
    let debris = car.join(".v9.1.2.tmp");
    fs::create_dir(&debris).unwrap();
    fs::File::open(&debris).unwrap().set_modified(hours_ago(1)).unwrap();
    let dir = store.version_dir("car", "v5").unwrap();
    assert_eq!(fs::read(dir.join("w.bin")).unwrap(), b"w");
    assert_eq!(cached(), [true, false, false, true, true]);
    assert!(!debris.exists());
    // Downloaded again when needed; all used within the grace period, none is deleted,
    // even beyond CACHE_KEEP.
    store.version_dir("car", "v2").unwrap();
    store.version_dir("car", "v3").unwrap();
    assert_eq!(cached(), [true; 5]);
    fs::remove_dir_all(&cache).unwrap();
}

#[test]
fn category_names_cannot_escape_the_store() {
    for good in ["car", "bus-2", "a_b", "0"] {
        assert!(valid_category(good), "{good}");
    }
    for bad in ["", "..", "../etc", "car/../x", "Car", "-car", "car.json", "a b", &"x".repeat(65)] {
        assert!(!valid_category(bad), "{bad:?}");
    }
}

#[test]
fn a_seed_is_imported_once_and_activated_as_generation_zero() {
    let root = temp("seed");
    let store = Store::open(&root).unwrap();
    store.probe().unwrap();
    let version = store.import_seed("car", &shipped()).unwrap();
    assert!(version.starts_with("seed-") && version.len() == 17, "{version}");
    assert_eq!(store.import_seed("car", &shipped()).unwrap(), version);
    let (generation, head) = store.head("car").unwrap().unwrap();
    assert_eq!((generation, head.version.as_str(), head.previous, head.actor.as_str()), (0, &*version, None, "seed"));
    assert_eq!(store.manifest("car", &version).unwrap().crop, [128, 320]);
    assert_eq!(store.categories().unwrap(), ["car"]);
    assert_eq!(store.versions("car").unwrap(), std::slice::from_ref(&version));
    assert!(root.join("models/car/activations/00000000000000000000.json").is_file());
    assert!(store.version_dir("car", &version).unwrap().join(MANIFEST).is_file());
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn activation_is_create_only_and_checks_the_expected_generation() {
    let root = temp("activate");
    let store = Store::open(&root).unwrap();
    let seed = store.import_seed("car", &shipped()).unwrap();
    // A second version (same files, another name) to switch between.
    store.upload_dir("models/car/versions/v2", &shipped(), None).unwrap();
    assert_eq!(store.activate("car", "v2", "test", "try", Some(0), None).unwrap(), 1);
    let err = store.activate("car", &seed, "test", "stale", Some(0), None).unwrap_err();
    assert!(matches!(err, StoreError::Conflict { expected: 0, found: 1, .. }), "{err}");
    assert!(matches!(store.activate("car", "nope", "t", "r", None, None), Err(StoreError::UnknownVersion { .. })));
    // Activating the active version is a no-op.
    assert_eq!(store.activate("car", "v2", "test", "again", Some(1), None).unwrap(), 1);
    assert_eq!(store.rollback("car", "test", "back", None).unwrap(), 2);
    let (generation, head) = store.head("car").unwrap().unwrap();
    // Rolled back to the seed, which nothing preceded: a second rollback has nowhere to go.
    assert_eq!((generation, head.version, head.previous), (2, seed.clone(), None));
    assert!(matches!(store.rollback("car", "test", "again", None), Err(StoreError::NoPrevious(_))));
    // A restart does not re-activate the seed over a newer activation... unless it is a seed.
    store.import_seed("car", &shipped()).unwrap();
    assert_eq!(store.head("car").unwrap().unwrap().0, 2);
    // create never overwrites.
    assert!(store.create("x.json", b"1".to_vec()).unwrap());
    assert!(!store.create("x.json", b"2".to_vec()).unwrap());
    assert_eq!(store.read("x.json").unwrap().unwrap(), b"1");
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn rollbacks_walk_back_through_the_log() {
    let root = temp("walk");
    let store = Store::open(&root).unwrap();
    let seed = store.import_seed("car", &shipped()).unwrap();
    for v in ["v2", "v3"] {
        store.upload_dir(&format!("models/car/versions/{v}"), &shipped(), None).unwrap();
        store.activate("car", v, "test", "next", None, None).unwrap();
    }
    let active = |store: &Store| store.head("car").unwrap().unwrap().1.version;
    store.rollback("car", "test", "undo v3", None).unwrap();
    assert_eq!(active(&store), "v2");
    store.rollback("car", "test", "undo v2", Some(3)).unwrap();
    assert_eq!(active(&store), seed, "the second rollback toggled back instead of walking back");
    assert!(matches!(store.rollback("car", "test", "undo seed", None), Err(StoreError::NoPrevious(_))));
    // A new activation starts a new trail: its rollback returns to the seed, then stops.
    store.activate("car", "v3", "test", "again", None, None).unwrap();
    store.rollback("car", "test", "undo v3 again", None).unwrap();
    assert_eq!(active(&store), seed);
    assert!(matches!(store.rollback("car", "test", "stop", None), Err(StoreError::NoPrevious(_))));
    fs::remove_dir_all(&root).unwrap();
}

#[test]
fn a_version_without_its_manifest_is_debris_and_is_replaced() {
    let root = temp("debris");
    let store = Store::open(&root).unwrap();
    store.create("models/car/versions/v3/mesh.safetensors", b"partial".to_vec()).unwrap();
    assert!(store.versions("car").unwrap().is_empty());
    assert!(matches!(store.manifest("car", "v3"), Err(StoreError::UnknownVersion { .. })));
    store
        .put_version("car", "v3", |dir| {
            fs::create_dir(dir).unwrap();
            for e in fs::read_dir(shipped()).unwrap() {
                let p = e.unwrap().path();
                fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
            }
            Ok(())
        })
        .unwrap();
    assert_eq!(store.versions("car").unwrap(), ["v3"]);
    let dir = store.version_dir("car", "v3").unwrap();
    assert_eq!(fs::read(dir.join("mesh.safetensors")).unwrap(), fs::read(shipped().join("mesh.safetensors")).unwrap());
    assert!(store.put_version("car", "v3", |_| Ok(())).is_err(), "versions are immutable");
    fs::remove_dir_all(&root).unwrap();
}
