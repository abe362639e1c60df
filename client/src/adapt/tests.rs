//! The upload ledger: acks, resends after BUFFER_FULL, and give-ups.

use target_ack::Status as AckStatus;

use super::*;

fn sha(bytes: &[u8]) -> String {
    format!("{:x}", Sha256::digest(bytes))
}

fn ack(image: &[u8], status: AckStatus, reason: &str) -> TargetAck {
    use target_ack::Rejection;
    let rejection = match (status, reason.split(':').next()) {
        (AckStatus::Rejected, Some("BUFFER_FULL")) => Rejection::BufferFull,
        (AckStatus::Rejected, _) => Rejection::InvalidImage,
        _ => Rejection::Unspecified,
    };
    let (sha256, status, rejection) = (sha(image), status as i32, rejection as i32);
    TargetAck { sha256, status, rejection, reason: reason.into(), ..Default::default() }
}

fn ledger_with(n: usize) -> Ledger {
    let mut ledger = Ledger::new(2, Duration::from_millis(100));
    for i in 0..n {
        ledger.admit(format!("{i}.png"), vec![i as u8]);
    }
    ledger
}

fn send_all(ledger: &mut Ledger) -> Vec<Vec<u8>> {
    let mut sent = Vec::new();
    while ledger.window_open() {
        match ledger.send_next("car") {
            Some(m) => sent.push(m.image),
            None => break,
        }
    }
    sent
}

fn names(uploads: &[Upload]) -> Vec<&str> {
    uploads.iter().map(|u| u.name.as_str()).collect()
}

#[test]
fn acks_match_images_in_order_and_the_window_is_bounded() {
    let mut ledger = ledger_with(WINDOW + 2);
    let sent = send_all(&mut ledger);
    assert_eq!(sent.len(), WINDOW, "no more than the window in flight");
    ledger.acked(ack(&sent[0], AckStatus::Accepted, "")).unwrap();
    ledger.acked(ack(&sent[1], AckStatus::Duplicate, "")).unwrap();
    let ready = ledger.take_ready();
    assert_eq!(names(&ready), ["0.png", "1.png"]);
    assert_eq!(ready[1].ack.status(), AckStatus::Duplicate);
    assert_eq!(send_all(&mut ledger), [vec![WINDOW as u8], vec![WINDOW as u8 + 1]]);
    // An ack for something else than the oldest image in flight is a protocol error.
    assert!(matches!(ledger.acked(ack(b"other", AckStatus::Accepted, "")), Err(Error::Protocol(_))));
}

#[test]
fn a_broken_stream_resends_exactly_the_unacknowledged_images() {
    let mut ledger = ledger_with(5);
    let sent = send_all(&mut ledger);
    ledger.acked(ack(&sent[0], AckStatus::Accepted, "")).unwrap();
    ledger.acked(ack(&sent[1], AckStatus::Accepted, "")).unwrap();
    ledger.broken();
    let resent = send_all(&mut ledger);
    assert_eq!(resent, [vec![2], vec![3], vec![4]], "the unacknowledged ones, in order");
    // Image 2 had been stored before the break: the resend is a DUPLICATE, which is final.
    ledger.acked(ack(&resent[0], AckStatus::Duplicate, "")).unwrap();
    ledger.acked(ack(&resent[1], AckStatus::Accepted, "")).unwrap();
    ledger.acked(ack(&resent[2], AckStatus::Rejected, "INVALID_IMAGE: not an image")).unwrap();
    let ready = ledger.take_ready();
    assert_eq!(names(&ready), ["0.png", "1.png", "2.png", "3.png", "4.png"]);
    assert_eq!(ready.iter().map(|u| u.sends).collect::<Vec<_>>(), [1, 1, 2, 2, 2]);
    assert!(ledger.is_idle());
}

#[test]
fn buffer_full_images_wait_then_are_resent_a_bounded_number_of_times() {
    let mut ledger = ledger_with(3);
    let sent = send_all(&mut ledger);
    ledger.acked(ack(&sent[0], AckStatus::Accepted, "")).unwrap();
    ledger.acked(ack(&sent[1], AckStatus::Rejected, "BUFFER_FULL: 1000 of 1000")).unwrap();
    assert!(!ledger.window_open(), "nothing new goes out while an image waits for space");
    assert_eq!(ledger.pause(), None, "not before the acks in flight are in");
    ledger.acked(ack(&sent[2], AckStatus::Accepted, "")).unwrap();
    // Image 2 is done but waits for image 1 to be yielded in order.
    assert_eq!(names(&ledger.take_ready()), ["0.png"]);
    assert_eq!(ledger.pause(), Some(Duration::from_millis(100)));
    ledger.release_waiting();

    let resent = send_all(&mut ledger);
    assert_eq!(resent, [vec![1]]);
    ledger.acked(ack(&resent[0], AckStatus::Rejected, "BUFFER_FULL: still")).unwrap();
    assert_eq!(ledger.pause(), Some(Duration::from_millis(200)), "the pause doubles");
    ledger.release_waiting();
    let resent = send_all(&mut ledger);
    // The third BUFFER_FULL (two resends allowed) is final.
    ledger.acked(ack(&resent[0], AckStatus::Rejected, "BUFFER_FULL: still")).unwrap();
    let ready = ledger.take_ready();
    assert_eq!(names(&ready), ["1.png", "2.png"]);
    assert!(buffer_full(&ready[0].ack) && ready[0].sends == 3);
    assert!(ledger.is_idle() && ledger.pause().is_none());
}

#[test]
fn waiting_images_go_before_new_ones_after_a_break() {
    let mut ledger = ledger_with(4);
    let sent = send_all(&mut ledger);
    ledger.acked(ack(&sent[0], AckStatus::Rejected, "BUFFER_FULL: full")).unwrap();
    ledger.acked(ack(&sent[1], AckStatus::Accepted, "")).unwrap();
    ledger.broken(); // 2 and 3 lost with the stream
    ledger.release_waiting();
    assert_eq!(send_all(&mut ledger), [vec![0], vec![2], vec![3]]);
}

#[test]
fn job_states() {
    assert!(is_terminal(JobState::Activated as i32) && is_terminal(JobState::Cancelled as i32));
    assert!(!is_terminal(JobState::Validating as i32) && !is_terminal(99));
    assert_eq!(state_name(JobState::Superseded as i32), "SUPERSEDED");
    assert_eq!(state_name(99), "UNKNOWN(99)");
    let (a, b) = (new_client_job_id(), new_client_job_id());
    assert!(a.starts_with("cli-") && a.len() == 36 && a != b);
}
