//! Unit tests of the client library (endpoint schemes, errors).

use super::*;

#[test]
fn bare_host_port_gets_a_scheme() {
    assert_eq!(with_scheme("127.0.0.1:50051", false), "http://127.0.0.1:50051");
    assert_eq!(with_scheme("127.0.0.1:50051", true), "https://127.0.0.1:50051");
    assert_eq!(with_scheme("https://pose.example:443", false), "https://pose.example:443");
}

#[test]
fn retries_follow_the_hint_or_back_off() {
    let plain = Status::unavailable("busy");
    assert!(delay(&plain, 0) >= BACKOFF && delay(&plain, 0) < BACKOFF * 2);
    assert!(delay(&plain, 3) >= BACKOFF * 8);
    assert!(delay(&plain, 30) <= MAX_BACKOFF * 2);
    let mut details = tonic_types::ErrorDetails::new();
    details.set_retry_info(Some(Duration::from_millis(700)));
    let hinted = Status::with_error_details(Code::Unavailable, "busy", details);
    assert!(delay(&hinted, 0) >= Duration::from_millis(700));
    assert!(retryable(&plain) && !retryable(&Status::invalid_argument("bad")));
}

#[test]
fn transport_failures_are_retried_server_answers_are_not() {
    let reset = std::io::Error::new(std::io::ErrorKind::ConnectionReset, "reset by peer");
    let broken = Status::from_error(Box::new(reset));
    assert!(transport_error(&broken) && retryable(&broken), "{broken:?}");
    assert_eq!(cause(&broken), "", "the message says it all");
    assert_eq!(cause(&Status::unavailable("busy")), "");
    // The same codes sent by the server are its answer.
    assert!(!retryable(&Status::internal("bug")) && !retryable(&Status::unknown("?")));
    assert!(!retryable(&Status::aborted("stale generation")));
}

/// hyper's way: a message, and the I/O error that says why as its source.
#[derive(Debug, thiserror::Error)]
#[error("tcp connect error")]
struct ConnectError(#[source] std::io::Error);

#[test]
fn a_transport_failure_names_its_cause() {
    let refused = std::io::Error::new(std::io::ErrorKind::ConnectionRefused, "connection refused");
    let status = Status::from_error(Box::new(ConnectError(refused)));
    assert_eq!((status.message(), cause(&status).as_str()), ("tcp connect error", ": connection refused"));
    let error = Error::GaveUp { status, tries: 3, endpoints: "a:1, b:2".into() };
    assert_eq!(error.to_string(), "Unknown: tcp connect error: connection refused (gave up after 3 tries on a:1, b:2)");
    assert_eq!(error.code(), Some(Code::Unknown));
}

fn entry(generation: u64, version: &str, previous: &str, reason: &str) -> ActivationEntry {
    ActivationEntry {
        generation,
        version: version.into(),
        previous: previous.into(),
        reason: reason.into(),
        ..Default::default()
    }
}

#[test]
fn a_lost_activation_reply_is_recognised_in_the_log() {
    let log = ListVersionsResponse {
        versions: vec![],
        activations: vec![
            entry(2, "job-b", "job-a", "try b"),
            entry(1, "job-a", "seed-1", ""),
            entry(0, "seed-1", "", ""),
        ],
    };
    assert_eq!(activation_landed(&log, 1, "job-b", "try b").map(|e| e.generation), Some(2));
    assert!(activation_landed(&log, 1, "job-b", "someone else's").is_none());
    assert!(activation_landed(&log, 0, "job-b", "try b").is_none(), "not the generation we expected");
    assert!(activation_landed(&log, 1, "job-c", "try b").is_none());

    // A rollback from generation 1 re-activates that entry's previous (seed-1).
    let log = ListVersionsResponse {
        versions: vec![],
        activations: vec![
            entry(2, "seed-1", "job-a", "bad"),
            entry(1, "job-a", "seed-1", ""),
            entry(0, "seed-1", "", ""),
        ],
    };
    assert_eq!(rollback_landed(&log, 1, "bad").map(|e| e.version.as_str()), Some("seed-1"));
    assert!(rollback_landed(&log, 1, "other").is_none());
    assert!(rollback_landed(&log, 0, "bad").is_none());
}

#[tokio::test]
async fn unreachable_server_is_a_connect_error() {
    // Port 1 on loopback is essentially never listening.
    let err = Client::connect("127.0.0.1:1").await.unwrap_err();
    assert!(matches!(err, Error::Connect { .. }), "{err:?}");
}
