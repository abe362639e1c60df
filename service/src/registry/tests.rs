//! The registry on an in-memory store: seeds imported and served, a new activation swapped in,
//! a stale one refused, a rollback, and categories that cannot load saying why.

use std::time::Instant;

use super::*;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-registry-{name}-{}", std::process::id()));
    let _ = fs::remove_dir_all(&dir);
    fs::create_dir_all(&dir).unwrap();
    dir
}

fn shipped_models() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models")
}

#[test]
fn seeds_are_served_then_swapped_refused_when_stale_and_rolled_back() {
    let dir = scratch("swap");
    let store = Store::in_memory(&dir.join("cache")).unwrap();
    let registry =
        Registry::start(store.clone(), &shipped_models(), &WorkerConfig::for_tests(), Arc::new(Metrics::new()))
            .unwrap();
    // Every shipped category is served, in name order.
    let mut shipped: Vec<String> = fs::read_dir(shipped_models())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join(MANIFEST).is_file())
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    shipped.sort();
    assert!(shipped.iter().any(|c| c == "car"), "{shipped:?}");
    assert_eq!(registry.categories().map(|c| c.name.clone()).collect::<Vec<_>>(), shipped);
    let car = registry.get("car").unwrap();
    let seed = car.active().expect("the seed is active");
    assert!(seed.version.starts_with("seed-"), "{}", seed.version);
    let deadline = Instant::now() + Duration::from_secs(300);
    while !registry.readiness().ready {
        assert!(Instant::now() < deadline, "not every seed loaded: {}", registry.readiness().reason);
        std::thread::sleep(Duration::from_millis(50));
    }
    let ready = registry.readiness();
    let all = format!("{n} of {n} models loaded", n = shipped.len());
    assert!(ready.reason == all, "{}", ready.reason);

    // A second version (the seed's files under another id), activated by another process.
    store
        .put_version("car", "v2", |out| {
            fs::create_dir_all(out).map_err(|e| e.to_string())?;
            for entry in fs::read_dir(&seed.dir).map_err(|e| e.to_string())? {
                let path = entry.map_err(|e| e.to_string())?.path();
                fs::copy(&path, out.join(path.file_name().unwrap())).map_err(|e| e.to_string())?;
            }
            Ok(())
        })
        .unwrap();
    store.activate("car", "v2", "test", "swap", Some(seed.generation), None).unwrap();
    registry.refresh();
    let v2 = car.active().unwrap();
    assert_eq!((v2.version.as_str(), v2.generation), ("v2", seed.generation + 1));
    // An activation from a stale generation loses (create-only log entries).
    let stale = store.activate("car", &seed.version, "test", "stale", Some(seed.generation), None);
    assert!(matches!(stale, Err(StoreError::Conflict { .. })), "{stale:?}");
    assert!(!car.refresh(&store).unwrap(), "nothing changed");
    // A rollback activates the previous version as a new generation.
    store.rollback("car", "test", "back", None).unwrap();
    registry.refresh();
    let back = car.active().unwrap();
    assert_eq!((back.version.as_str(), back.generation), (seed.version.as_str(), seed.generation + 2));
    fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_category_that_cannot_load_is_not_ready_and_says_why() {
    let dir = scratch("broken");
    let seeds = dir.join("seeds");
    fs::create_dir_all(seeds.join("bus")).unwrap();
    fs::write(seeds.join("bus").join(MANIFEST), b"{ not json").unwrap();
    // The car model put in the chair folder.
    fs::create_dir_all(seeds.join("chair")).unwrap();
    fs::copy(shipped_models().join("car").join(MANIFEST), seeds.join("chair").join(MANIFEST)).unwrap();
    let store = Store::in_memory(&dir.join("cache")).unwrap();
    let registry = Registry::start(store, &seeds, &WorkerConfig::for_tests(), Arc::new(Metrics::new())).unwrap();
    let bus = registry.get("bus").expect("the failed seed is still listed");
    assert!(bus.active().is_none() && !bus.ready());
    assert!(bus.error().is_some_and(|e| !e.is_empty()), "{:?}", bus.error());
    let chair = registry.get("chair").unwrap();
    assert!(chair.active().is_none() && !chair.ready());
    assert!(chair.error().is_some_and(|e| e.contains(r#"category "car" in the folder of category "chair""#)));
    let readiness = registry.readiness();
    assert!(!readiness.ready && readiness.reason.contains("bus: "), "{}", readiness.reason);
    fs::remove_dir_all(dir).unwrap();
}
