use serde::Serialize;
use serde_json::{Value, json};
use udapose_proto::v1 as pb;

use crate::*;

fn pose() -> PoseAnswer {
    PoseAnswer {
        azimuth: 1.0,
        elevation: 0.2,
        theta: -0.1,
        azimuth_deg: 57.3,
        elevation_deg: 11.5,
        theta_deg: -5.7,
        distance: 5.0,
        rotation: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        score: 0.8,
        hypotheses: vec![HypothesisAnswer { azimuth: 1.0, elevation: 0.2, theta: -0.1, distance: 5.0, score: 0.8 }],
        runner_up_gap: Some(0.01),
        crop_box: BoxAnswer { x0: 1.0, y0: 2.0, x1: 30.0, y1: 40.0 },
        cuboid: vec![0.5; 16],
        model_version: "seed-1".into(),
    }
}

fn event() -> JobEvent {
    JobEvent {
        job_id: "j1".into(),
        seq: 3,
        state: JobState::Validating,
        time: 10.5,
        message: "gate".into(),
        round: 2,
        max_rounds: 5,
        fired_ratio: 0.4,
        pose_change_median_deg: Some(3.0),
        images_used: 48,
        images_held_out: 12,
        eta_seconds: 0.0,
        gate: vec![GateCriterion {
            name: "score_margin".into(),
            active: 0.1,
            candidate: 0.2,
            threshold: 0.15,
            passed: true,
            detail: String::new(),
        }],
        version: "v2".into(),
    }
}

fn job() -> JobView {
    JobView {
        job_id: "j1".into(),
        category: "car".into(),
        state: JobState::Activated,
        source_version: "seed-1".into(),
        source_generation: 0,
        version: "v2".into(),
        created: 1.0,
        updated: 2.0,
        images_used: 48,
        images_held_out: 12,
        reason: String::new(),
        client_job_id: "mine".into(),
        last_event: event(),
    }
}

fn activation(job_id: Option<&str>) -> ActivationEntry {
    ActivationEntry {
        category: "car".into(),
        generation: 1,
        version: "v2".into(),
        previous: Some("seed-1".into()),
        actor: "job".into(),
        reason: "gate passed".into(),
        time: 5,
        job_id: job_id.map(Into::into),
    }
}

/// The property names of schema `name` (following one `$ref` level is not needed: every
/// nested type is its own schema).
fn properties(name: &str) -> Vec<String> {
    let schemas = schemas();
    let props = schemas[name]["properties"].as_object().unwrap_or_else(|| panic!("{name}: {:#}", schemas[name]));
    let mut keys: Vec<String> = props.keys().cloned().collect();
    keys.sort();
    keys
}

fn keys(value: impl Serialize) -> Vec<String> {
    let mut keys: Vec<String> = serde_json::to_value(value).unwrap().as_object().unwrap().keys().cloned().collect();
    keys.sort();
    keys
}

#[test]
fn every_schema_lists_exactly_the_fields_serde_writes() {
    let description = ModelDescription {
        category: "car".into(),
        version: "seed-1".into(),
        ready: true,
        generation: 0,
        trained_as: "seed-1".into(),
        backbone: "resnet18".into(),
        feature_dim: 128,
        vertices: 1054,
        crop_height: 128,
        crop_width: 320,
        cuboid: vec![0.0; 6],
        error: String::new(),
        manifest: json!({ "category": "car" }),
    };
    let summary = ModelSummary { category: "car".into(), version: None, ready: false, error: Some("no model".into()) };
    let cases: Vec<(&str, Vec<String>)> = vec![
        ("PoseEstimate", keys(pose())),
        ("Hypothesis", keys(&pose().hypotheses[0])),
        ("Box", keys(pose().crop_box)),
        ("Timings", keys(Timings::default())),
        (
            "EstimateResponse",
            keys(EstimateAnswer {
                estimates: vec![],
                model_version: "v".into(),
                frame_id: "f".into(),
                timings: Timings::default(),
            }),
        ),
        ("Error", keys(ErrorBody::new("NOT_FOUND", "no such route"))),
        ("ErrorDetail", keys(ErrorBody::new("NOT_FOUND", "x").error)),
        ("Model", keys(&summary)),
        ("Models", keys(ModelList { models: vec![summary.clone()] })),
        ("ModelDescription", keys(&description)),
        ("GateCriterion", keys(&event().gate[0])),
        ("JobEvent", keys(event())),
        ("Job", keys(job())),
        ("Jobs", keys(JobList { jobs: vec![] })),
        ("Version", keys(VersionView { version: "v".into(), trained_as: "v".into(), active: true, job_id: None })),
        ("Activation", keys(activation(Some("j1")))),
        ("Versions", keys(Versions { versions: vec![], activations: vec![] })),
    ];
    for (name, written) in cases {
        assert_eq!(properties(name), written, "schema {name}");
    }
    let states = schemas()["JobState"]["enum"].clone();
    assert_eq!(
        states,
        json!(["QUEUED", "RUNNING", "VALIDATING", "ACTIVATED", "REJECTED", "SUPERSEDED", "FAILED", "CANCELLED"])
    );
    assert_eq!(serde_json::to_value(JobState::Superseded).unwrap(), json!("SUPERSEDED"));
}

#[test]
fn nested_types_are_references_to_their_own_schemas() {
    let s = schemas();
    assert_eq!(s["PoseEstimate"]["properties"]["crop_box"]["$ref"], "#/components/schemas/Box");
    assert_eq!(s["PoseEstimate"]["properties"]["hypotheses"]["items"]["$ref"], "#/components/schemas/Hypothesis");
    assert_eq!(s["Job"]["properties"]["last_event"]["$ref"], "#/components/schemas/JobEvent");
    assert_eq!(s["EstimateResponse"]["properties"]["estimates"]["items"]["$ref"], "#/components/schemas/PoseEstimate");
}

/// What the CLI prints from a gRPC answer is what HTTP would have sent for the same data.
#[test]
fn grpc_messages_convert_back_to_the_same_json() {
    let answer = EstimateAnswer {
        estimates: vec![pose()],
        model_version: "seed-1".into(),
        frame_id: "f7".into(),
        timings: Timings { decode_ms: 1.0, total_ms: 9.0, batch_size: 2, ..Timings::default() },
    };
    assert_eq!(EstimateAnswer::from(pb::EstimateResponse::from(answer.clone())), answer);
    assert_eq!(JobView::try_from(pb::Job::from(job())).unwrap(), job());
    for job_id in [None, Some("j1")] {
        assert_eq!(ActivationEntry::from(pb::ActivationEntry::from(activation(job_id))), activation(job_id));
    }
    let version = VersionView { version: "seed-1".into(), trained_as: "seed-1".into(), active: true, job_id: None };
    assert_eq!(VersionView::from(pb::VersionInfo::from(version.clone())), version);
    let summary = ModelSummary { category: "car".into(), version: Some("seed-1".into()), ready: true, error: None };
    assert_eq!(ModelSummary::from(pb::ModelInfo::from(summary.clone())), summary);
}

#[test]
fn an_unknown_grpc_state_is_an_error_not_a_guess() {
    let mut j = pb::Job::from(job());
    j.state = 0;
    assert_eq!(JobView::try_from(j).unwrap_err(), UnknownState(0));
    assert_eq!(JobState::try_from(42), Err(UnknownState(42)));
    let absent: Value =
        serde_json::to_value(ModelSummary { category: "car".into(), version: None, ready: false, error: None })
            .unwrap();
    assert_eq!(absent, json!({ "category": "car", "version": null, "ready": false }));
}
