//! Hot swap: a version activated in the store by another process (a create-only activation
//! file, as adaptation jobs and other replicas write it) is picked up by the running server,
//! and answers name the version that computed them. Needs `make test`'s quick model and data.

mod support;

use std::{
    fs,
    time::{Duration, Instant},
};

use serde_json::json;
use support::{Server, quick_images};

#[test]
fn a_new_activation_is_served_without_a_restart() {
    let server = Server::config("swap").quick_model().arg("--poll").arg("1").start();
    let image = quick_images("source", 1).remove(0);
    let first = server.request("POST", "/v1/pose/car", &[], &image.bytes).json();
    let seed = first["model_version"].as_str().unwrap().to_owned();
    assert!(seed.starts_with("seed-"));

    // Another writer adds version "v2" (the same weights under a new name) and activates it.
    let car = server.store_dir().join("models/car");
    let v2 = car.join("versions/v2");
    fs::create_dir_all(&v2).unwrap();
    for f in fs::read_dir(car.join("versions").join(&seed)).unwrap().map(|e| e.unwrap().path()) {
        fs::copy(&f, v2.join(f.file_name().unwrap())).unwrap();
    }
    let activation = json!({ "version": "v2", "previous": seed, "actor": "test", "reason": "swap", "time": 0 });
    fs::write(car.join("activations/00000000000000000001.json"), activation.to_string()).unwrap();

    let deadline = Instant::now() + Duration::from_secs(30);
    let swapped = loop {
        let answer = server.request("POST", "/v1/pose/car", &[], &image.bytes).json();
        if answer["model_version"] == "v2" {
            break answer;
        }
        assert_eq!(answer["model_version"], seed.as_str(), "served by neither version");
        assert!(Instant::now() < deadline, "v2 never served\n{}", server.log());
        std::thread::sleep(Duration::from_millis(200));
    };
    // Same weights, so the same answer; the version is the new one everywhere.
    assert_eq!(swapped["estimates"][0]["azimuth"], first["estimates"][0]["azimuth"]);
    assert_eq!(swapped["estimates"][0]["model_version"], "v2");
    let (_, models) = server.get("/v1/models");
    assert!(models.contains("\"version\":\"v2\""), "{models}");
    let (_, described) = server.get("/v1/models/car");
    assert!(described.contains("\"generation\":1"), "{described}");
}
