//! Per-domain experts against a real server (issue "Continual online adaptation"): a job that
//! wins its own domain but would regress an earlier one is kept as an expert of the version it
//! started from, so each domain keeps the model that won it. Needs `make test`'s quick model
//! and data.

mod support;

use support::jobs::*;
use support::{QuickImage, Server, quick_images};

/// Each image's estimated angles, as the server answers them now.
fn angles(server: &Server, images: &[QuickImage]) -> Vec<[f64; 3]> {
    images
        .iter()
        .map(|image| {
            let p = &estimate(server, image)["estimates"][0];
            ["azimuth", "elevation", "theta"].map(|k| p[k].as_f64().unwrap())
        })
        .collect()
}

fn right(server: &Server, images: &[QuickImage]) -> usize {
    accuracy(server, images).0.iter().filter(|&&h| h).count()
}

#[test]
fn a_job_that_would_regress_an_earlier_domain_is_kept_as_an_expert() {
    // As in adapt.rs: to the quick model fog is far enough that the target check is off here.
    // The quick model is retrained on every CI run, and whether the clear job's median margin
    // rises over the fog model's on 15 held-out images varies with it (0.135 → 0.095 on one
    // run): the margin may fall here, so the verdict on the clear images rests on flip
    // consistency and pose diversity. This test is about what the gate does with a candidate
    // that wins its own images and would regress an earlier set.
    let server = server_with("experts", &["--min-target-fired", "0", "--margin-gain=-1"]);
    let (clear, fog) = (quick_images("source", 60), quick_images("corrupt/fog", 60));

    // Step 1: fog, activated as the version's own model (adapt.rs). Its regression set holds
    // 8 held-out images; 24 more fog images as anchors give the expert's rival enough of them.
    let fog_job = job_on(&server, "corrupt/fog");
    assert_eq!(fog_job["state"], "ACTIVATED", "{fog_job}\n{}", server.log());
    let fog_version = fog_job["version"].as_str().unwrap().to_owned();
    let mut anchors: Vec<_> =
        std::fs::read_dir(adapt_images("corrupt/fog")).unwrap().map(|e| e.unwrap().path()).collect();
    anchors.sort();
    for path in &anchors[..24] {
        let r = server.request("POST", "/v1/adapt/car/images?anchor=true", &[], &std::fs::read(path).unwrap());
        assert_eq!(r.status, 200, "{}", r.body);
    }
    let (fog_model_fog, fog_model_clear_right) = (angles(&server, &fog), right(&server, &clear));

    // Step 2: clear images. As one shared model the candidate gives back fog (adapt.rs); kept
    // as an expert that answers the images like its own, it leaves fog to step 1's model.
    let job = job_on(&server, "source");
    let message = job["last_event"]["message"].as_str().unwrap_or_default().to_owned();
    eprintln!("{}: {message}", job["state"]);
    assert_eq!(job["state"], "ACTIVATED", "{job}\n{}", server.log());
    let candidate = job["version"].as_str().unwrap();
    let composite = format!("{candidate}-experts");
    assert_eq!(active_version(&server), composite);
    assert!(message.contains("answering the images like its own"), "{message}");
    let gate = job["last_event"]["gate"].as_array().unwrap();
    assert!(gate.iter().any(|c| c["name"].as_str().unwrap().contains('/') && c["passed"] == false), "{gate:?}");

    // The composite answers fog images as step 1's model did, bit for bit where the clear
    // domain leaves them (almost all), and clear images as the candidate does.
    let (composite_fog, composite_clear_right) = (angles(&server, &fog), right(&server, &clear));
    let same = fog_model_fog.iter().zip(&composite_fog).filter(|(a, b)| a == b).count();
    let (_, body) = server.get("/v1/models/car/versions");
    assert!(body.contains(&composite) && body.contains(candidate), "{body}");
    serve_version(&server, candidate, &fog[0]);
    let (candidate_clear_right, candidate_fog) = (right(&server, &clear), angles(&server, &fog));
    let candidate_same = fog_model_fog.iter().zip(&candidate_fog).filter(|(a, b)| a == b).count();
    serve_version(&server, &composite, &fog[0]);
    eprintln!(
        "fog test: composite answers {same}/60 as step 1's model, the candidate alone {candidate_same}/60; \
         clear test Acc@π/6: step 1's model {fog_model_clear_right}/60, candidate {candidate_clear_right}/60, \
         composite {composite_clear_right}/60"
    );
    assert!(same >= 57, "{same} of 60 fog images answered as step 1's model did");
    assert!(
        composite_clear_right + 3 >= candidate_clear_right,
        "clear: {composite_clear_right} vs {candidate_clear_right}"
    );

    // Step 3: clear images again. Most go to the clear expert, so the job adapts the expert,
    // and the gate compares it with the expert on the images the expert answers: step 2's set,
    // not the fog set or the fog anchors, which the version's own tensors answer.
    let again = job_on(&server, "source");
    eprintln!("{}: {}", again["state"], again["reason"]);
    let names: Vec<&str> =
        again["last_event"]["gate"].as_array().unwrap().iter().filter_map(|c| c["name"].as_str()).collect();
    let clear_set = format!("{}/score_margin", job["job_id"].as_str().unwrap());
    assert!(names.contains(&clear_set.as_str()), "{names:?}");
    assert!(!names.iter().any(|n| n.starts_with("anchor/") || n.starts_with(fog_job["job_id"].as_str().unwrap())));
    if again["state"] == "ACTIVATED" {
        let version = format!("{}-experts", again["version"].as_str().unwrap());
        assert_eq!(active_version(&server), version);
        let same = angles(&server, &fog).iter().zip(&fog_model_fog).filter(|(a, b)| a == b).count();
        assert!(same >= 57, "{same} of 60 fog images answered as step 1's model did");
    } else {
        assert_eq!(again["state"], "REJECTED", "{again}");
        assert_eq!(active_version(&server), composite);
    }
    serve_version(&server, &fog_version, &fog[0]);
}
