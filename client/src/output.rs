//! What the `udapose` CLI prints for adaptation, jobs and model versions: the text lines (a
//! stable format that scripts and tests may match, documented in `udapose adapt --help`) and
//! the JSON objects (the HTTP API's: `udapose-api`'s types, converted from the gRPC messages).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};
use udapose_api::{self as api, UnknownState};
use udapose_client::{
    ActivationEntry, GateCriterion, Job, JobEvent, JobState, ListVersionsResponse, Upload, state_name, target_ack,
};

/// The PNG, JPEG and WebP files directly in `dir` (not in its subfolders), sorted by path.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        bail!("{} is not a folder", dir.display());
    }
    let mut images: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("listing {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && is_image(p))
        .collect();
    images.sort();
    if images.is_empty() {
        bail!("{} holds no PNG, JPEG or WebP files", dir.display());
    }
    Ok(images)
}

pub fn is_image(path: &Path) -> bool {
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg" | "webp"))
}

/// The tally of an upload, for the progress bar and the summary.
#[derive(Debug, Default)]
pub struct UploadSummary {
    pub category: String,
    pub images: usize,
    pub accepted: usize,
    pub duplicate: usize,
    /// (image name, reason) of each rejected image.
    pub rejected: Vec<(String, String)>,
    /// Images sent more than once (a broken stream, or BUFFER_FULL).
    pub resent: usize,
    /// The buffer's fill and size after the last ack (the anchor set's, for anchors).
    pub buffered: u32,
    pub capacity: u32,
    /// Whether the images went to the category's anchor set.
    pub anchor: bool,
}

impl UploadSummary {
    pub fn new(category: &str) -> Self {
        UploadSummary { category: category.into(), ..Default::default() }
    }

    pub fn add(&mut self, upload: &Upload) {
        self.images += 1;
        match upload.ack.status() {
            target_ack::Status::Accepted => self.accepted += 1,
            target_ack::Status::Duplicate => self.duplicate += 1,
            target_ack::Status::Rejected | target_ack::Status::Unspecified => {
                let reason = if upload.ack.reason.is_empty() { "no reason given" } else { &upload.ack.reason };
                self.rejected.push((upload.name.clone(), reason.to_owned()));
            }
        }
        if upload.sends > 1 {
            self.resent += 1;
        }
        self.buffered = upload.ack.buffered;
        self.capacity = upload.ack.capacity;
    }

    /// `58 accepted, 1 duplicate, 1 rejected`: the progress bar's message.
    pub fn counts(&self) -> String {
        format!("{} accepted, {} duplicate, {} rejected", self.accepted, self.duplicate, self.rejected.len())
    }

    /// `uploaded 60 images to car: 58 accepted, 1 duplicate, 1 rejected (buffer 59/1000)`,
    /// then `rejected <name>: <reason>` per rejected image.
    pub fn lines(&self) -> Vec<String> {
        let mut lines = vec![format!(
            "uploaded {} images to {}: {} ({} {}/{})",
            self.images,
            self.category,
            self.counts(),
            if self.anchor { "anchor set" } else { "buffer" },
            self.buffered,
            self.capacity
        )];
        lines.extend(self.rejected.iter().map(|(name, reason)| format!("rejected {name}: {reason}")));
        lines
    }

    pub fn json(&self) -> Value {
        let rejected: Vec<_> = self.rejected.iter().map(|(n, r)| json!({ "image": n, "reason": r })).collect();
        json!({ "uploads": {
            "category": self.category, "images": self.images, "accepted": self.accepted,
            "duplicate": self.duplicate, "rejected": rejected, "resent": self.resent,
            "buffered": self.buffered, "capacity": self.capacity, "anchor": self.anchor,
        }})
    }
}

/// `#3 RUNNING round 2/5 fired 0.412 change 3.10° used 48 held-out 12 eta 40s[ version V][: message]`;
/// `change -` before round 2, `eta -` when unknown or done.
pub fn event_line(e: &JobEvent) -> String {
    let change = e.pose_change_median_deg.map_or("-".to_owned(), |d| format!("{d:.2}°"));
    let mut line = format!(
        "#{} {} round {}/{} fired {:.3} change {change} used {} held-out {} eta {}",
        e.seq,
        state_name(e.state),
        e.round,
        e.max_rounds,
        e.fired_ratio,
        e.images_used,
        e.images_held_out,
        duration(e.eta_seconds)
    );
    if !e.version.is_empty() {
        line += &format!(" version {}", e.version);
    }
    if !e.message.is_empty() {
        line += &format!(": {}", e.message);
    }
    line
}

/// `  gate score_margin active 0.0210 candidate 0.0350 threshold 0.0260 passed[ (detail)]`
/// (`FAILED` when it did not pass).
pub fn gate_line(c: &GateCriterion) -> String {
    let verdict = if c.passed { "passed" } else { "FAILED" };
    let mut line = format!(
        "  gate {} active {:.4} candidate {:.4} threshold {:.4} {verdict}",
        c.name, c.active, c.candidate, c.threshold
    );
    if !c.detail.is_empty() {
        line += &format!(" ({})", c.detail);
    }
    line
}

/// The last line for a job that ended: `job <ID> ACTIVATED version <VERSION>`, or
/// `job <ID> <STATE>: <reason>`; a job still going: `job <ID> <STATE>`.
pub fn final_line(job_id: &str, state: i32, version: &str, reason: &str) -> String {
    let name = state_name(state);
    match JobState::try_from(state) {
        Ok(JobState::Activated) => format!("job {job_id} ACTIVATED version {version}"),
        _ if udapose_client::is_terminal(state) => {
            let reason = if reason.is_empty() { "no reason given" } else { reason };
            format!("job {job_id} {name}: {reason}")
        }
        _ => format!("job {job_id} {name}"),
    }
}

/// `final_line` of a job as the server returned it; the reason falls back on the last event's
/// message.
pub fn job_final_line(job: &Job) -> String {
    let message = job.last_event.as_ref().map_or("", |e| e.message.as_str());
    let reason = if job.reason.is_empty() { message } else { &job.reason };
    let version =
        if job.version.is_empty() { job.last_event.as_ref().map_or("", |e| &e.version) } else { &job.version };
    final_line(&job.job_id, job.state, version, reason)
}

/// `job <ID> <STATE> category <C> from <SOURCE_VERSION> (generation <G>)`: what StartJob
/// returned.
pub fn job_started_line(job: &Job) -> String {
    format!(
        "job {} {} category {} from {} (generation {})",
        job.job_id,
        state_name(job.state),
        job.category,
        dash(&job.source_version),
        job.source_generation
    )
}

/// One job in detail, `key value` per line.
pub fn job_lines(job: &Job) -> Vec<String> {
    let mut lines = vec![
        format!("job          {}", job.job_id),
        format!("category     {}", job.category),
        format!("state        {}", state_name(job.state)),
        format!("source       {} (generation {})", dash(&job.source_version), job.source_generation),
        format!("version      {}", dash(&job.version)),
        format!("images       {} used, {} held out", job.images_used, job.images_held_out),
        format!("created      {}", utc(job.created)),
        format!("updated      {}", utc(job.updated)),
        format!("client id    {}", dash(&job.client_job_id)),
        format!("reason       {}", dash(&job.reason)),
    ];
    if let Some(e) = &job.last_event {
        lines.push(format!("last event   {}", event_line(e)));
        lines.extend(e.gate.iter().map(gate_line));
    }
    lines
}

/// `JOB  CATEGORY  STATE  ROUND  IMAGES  VERSION  UPDATED  REASON`, one row per job.
pub fn jobs_table(jobs: &[Job]) -> Vec<String> {
    if jobs.is_empty() {
        return vec!["no jobs".into()];
    }
    let rows: Vec<[String; 8]> = jobs
        .iter()
        .map(|j| {
            let round = j.last_event.as_ref().map_or("-".into(), |e| format!("{}/{}", e.round, e.max_rounds));
            [
                j.job_id.clone(),
                j.category.clone(),
                state_name(j.state),
                round,
                format!("{}+{}", j.images_used, j.images_held_out),
                dash(&j.version).to_owned(),
                utc(j.updated),
                dash(&j.reason).to_owned(),
            ]
        })
        .collect();
    table(["JOB", "CATEGORY", "STATE", "ROUND", "IMAGES", "VERSION", "UPDATED", "REASON"], &rows)
}

/// The regression sets table: `SET  KIND  VERSION  IMAGES  CREATED`.
pub fn regression_sets_table(sets: &[udapose_proto::v1::RegressionSet]) -> Vec<String> {
    if sets.is_empty() {
        return vec!["no regression sets (an activated job leaves its held-out images here)".into()];
    }
    let rows: Vec<[String; 5]> = sets
        .iter()
        .map(|s| {
            let created = if s.created > 0.0 { utc(s.created) } else { "-".into() };
            [s.set_id.clone(), s.kind.clone(), dash(&s.version).to_owned(), s.images.to_string(), created]
        })
        .collect();
    table(["SET", "KIND", "VERSION", "IMAGES", "CREATED"], &rows)
}

/// The versions table (`VERSION  ACTIVE  TRAINED_AS  JOB`), a blank line, and the activation
/// log (`GENERATION  VERSION  PREVIOUS  ACTOR  TIME  REASON`, newest first).
pub fn versions_lines(v: &ListVersionsResponse) -> Vec<String> {
    let versions: Vec<[String; 4]> = v
        .versions
        .iter()
        .map(|x| {
            let active = if x.active { "yes" } else { "no" };
            [x.version.clone(), active.into(), dash(&x.trained_as).into(), dash(&x.job_id).into()]
        })
        .collect();
    let log: Vec<[String; 6]> = v
        .activations
        .iter()
        .map(|a| {
            [
                a.generation.to_string(),
                a.version.clone(),
                dash(&a.previous).into(),
                dash(&a.actor).into(),
                utc(a.time as f64),
                dash(&a.reason).into(),
            ]
        })
        .collect();
    let mut lines = table(["VERSION", "ACTIVE", "TRAINED_AS", "JOB"], &versions);
    lines.push(String::new());
    lines.extend(table(["GENERATION", "VERSION", "PREVIOUS", "ACTOR", "TIME", "REASON"], &log));
    lines
}

/// `activated car version <V> generation <G> (previous <P>)`, or `rolled back car to ...`.
pub fn activation_line(verb: &str, e: &ActivationEntry) -> String {
    format!("{verb} {} version {} generation {} (previous {})", e.category, e.version, e.generation, dash(&e.previous))
}

// The JSON below is the HTTP API's own (udapose-api's types), converted from the gRPC messages.

pub fn event_json(e: &JobEvent) -> Result<Value, UnknownState> {
    Ok(to_value(api::JobEvent::try_from(e.clone())?))
}

pub fn job_json(j: &Job) -> Result<Value, UnknownState> {
    Ok(to_value(api::JobView::try_from(j.clone())?))
}

/// `{"result": {job_id, state, version, reason}}`: the last line of `adapt --json` and
/// `jobs watch --json`.
pub fn result_json(job_id: &str, state: i32, version: &str, reason: &str) -> Result<Value, UnknownState> {
    let state = api::JobState::try_from(state)?;
    Ok(json!({ "result": { "job_id": job_id, "state": state, "version": version, "reason": reason } }))
}

pub fn versions_json(v: &ListVersionsResponse) -> Value {
    to_value(api::Versions::from(v.clone()))
}

pub fn activation_json(a: &ActivationEntry) -> Value {
    to_value(api::ActivationEntry::from(a.clone()))
}

/// Serialising plain data structs cannot fail.
pub fn to_value(v: impl serde::Serialize) -> Value {
    serde_json::to_value(v).expect("plain data serialises")
}

fn dash(s: &str) -> &str {
    if s.is_empty() { "-" } else { s }
}

/// Columns padded to their widest cell (the last one not padded).
fn table<const N: usize>(header: [&str; N], rows: &[[String; N]]) -> Vec<String> {
    let mut widths = header.map(str::len);
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let line = |cells: Vec<&str>| {
        let mut out = String::new();
        for (i, cell) in cells.iter().enumerate() {
            if i + 1 == N {
                out += cell;
            } else {
                out += &format!("{cell:w$}  ", w = widths[i]);
            }
        }
        out.trim_end().to_owned()
    };
    let mut lines = vec![line(header.to_vec())];
    lines.extend(rows.iter().map(|r| line(r.iter().map(String::as_str).collect())));
    lines
}

/// `42s`, `3m05s`, `1h02m`; `-` for 0 (unknown or done).
pub fn duration(seconds: f64) -> String {
    if !seconds.is_finite() || seconds <= 0.0 {
        return "-".into();
    }
    let s = seconds.round() as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, s % 3600 / 60),
    }
}

/// Seconds since the Unix epoch as `2025-11-26T14:07:03Z`; `-` for 0.
pub fn utc(seconds: f64) -> String {
    if !seconds.is_finite() || seconds <= 0.0 {
        return "-".into();
    }
    let s = seconds.floor() as i64;
    let (days, rem) = (s.div_euclid(86_400), s.rem_euclid(86_400));
    // Days to a civil date (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z", rem / 3600, rem % 3600 / 60, rem % 60)
}

#[cfg(test)]
mod tests {
    use udapose_client::{TargetAck, VersionInfo};

    use super::*;

    fn event() -> JobEvent {
        JobEvent {
            job_id: "j1".into(),
            seq: 3,
            state: JobState::Running as i32,
            round: 2,
            max_rounds: 5,
            fired_ratio: 0.41234,
            pose_change_median_deg: Some(3.1),
            images_used: 48,
            images_held_out: 12,
            eta_seconds: 40.2,
            message: "round 2 done".into(),
            ..Default::default()
        }
    }

    #[test]
    fn event_lines_are_stable() {
        let mut e = event();
        assert_eq!(
            event_line(&e),
            "#3 RUNNING round 2/5 fired 0.412 change 3.10° used 48 held-out 12 eta 40s: round 2 done"
        );
        e.pose_change_median_deg = None;
        e.eta_seconds = 0.0;
        e.message.clear();
        e.state = JobState::Validating as i32;
        e.version = "j1".into();
        assert_eq!(event_line(&e), "#3 VALIDATING round 2/5 fired 0.412 change - used 48 held-out 12 eta - version j1");
        let c = GateCriterion {
            name: "score_margin".into(),
            active: 0.021,
            candidate: 0.035,
            threshold: 0.026,
            passed: true,
            detail: String::new(),
        };
        assert_eq!(gate_line(&c), "  gate score_margin active 0.0210 candidate 0.0350 threshold 0.0260 passed");
        let c = GateCriterion { passed: false, detail: "median over 12".into(), ..c };
        assert!(gate_line(&c).ends_with("FAILED (median over 12)"));
        let j = event_json(&e).unwrap();
        assert_eq!(j["state"], "VALIDATING");
        assert_eq!(j["pose_change_median_deg"], Value::Null);
        e.state = 0;
        assert!(event_json(&e).unwrap_err().to_string().contains("job state 0"));
    }

    #[test]
    fn final_lines_name_the_version_or_the_reason() {
        assert_eq!(final_line("j1", JobState::Activated as i32, "j1", ""), "job j1 ACTIVATED version j1");
        assert_eq!(
            final_line("j1", JobState::Rejected as i32, "j1", "pose_diversity: 0.7 < 0.9"),
            "job j1 REJECTED: pose_diversity: 0.7 < 0.9"
        );
        assert_eq!(final_line("j1", JobState::Cancelled as i32, "", ""), "job j1 CANCELLED: no reason given");
        assert_eq!(final_line("j1", JobState::Running as i32, "", ""), "job j1 RUNNING");
        // The reason falls back on the last event's message, the version on the event's.
        let job = Job {
            job_id: "j2".into(),
            state: JobState::Failed as i32,
            last_event: Some(JobEvent { message: "out of memory".into(), ..event() }),
            ..Default::default()
        };
        assert_eq!(job_final_line(&job), "job j2 FAILED: out of memory");
    }

    #[test]
    fn upload_summary_counts_and_lists_rejections() {
        let upload = |name: &str, status: target_ack::Status, reason: &str, sends| Upload {
            name: name.into(),
            ack: TargetAck {
                status: status as i32,
                reason: reason.into(),
                buffered: 7,
                capacity: 100,
                ..Default::default()
            },
            sends,
        };
        let mut s = UploadSummary::new("car");
        s.add(&upload("a.png", target_ack::Status::Accepted, "", 1));
        s.add(&upload("b.png", target_ack::Status::Duplicate, "", 2));
        s.add(&upload("c.png", target_ack::Status::Rejected, "INVALID_IMAGE: cannot decode", 1));
        assert_eq!(
            s.lines(),
            [
                "uploaded 3 images to car: 1 accepted, 1 duplicate, 1 rejected (buffer 7/100)",
                "rejected c.png: INVALID_IMAGE: cannot decode",
            ]
        );
        let j = s.json();
        assert_eq!(j["uploads"]["resent"], 1);
        assert_eq!(j["uploads"]["rejected"][0]["reason"], "INVALID_IMAGE: cannot decode");
    }

    #[test]
    fn folder_listing_is_sorted_flat_and_images_only() {
        let dir = std::env::temp_dir().join(format!("udapose-list-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("sub.png")).unwrap();
        for name in ["b.PNG", "a.jpg", "c.webp", "d.jpeg", "notes.txt", "sub.png/inner.png"] {
            std::fs::write(dir.join(name), b"x").unwrap();
        }
        let names: Vec<String> =
            list_images(&dir).unwrap().iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["a.jpg", "b.PNG", "c.webp", "d.jpeg"]);
        let empty = dir.join("sub.png");
        std::fs::remove_file(empty.join("inner.png")).unwrap();
        assert!(list_images(&empty).unwrap_err().to_string().contains("holds no PNG"));
        assert!(list_images(&dir.join("a.jpg")).unwrap_err().to_string().contains("is not a folder"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn tables_times_and_durations() {
        assert_eq!(utc(0.0), "-");
        assert_eq!(utc(1_764_166_023.7), "2025-11-26T14:07:03Z");
        assert_eq!(utc(951_782_400.0), "2000-02-29T00:00:00Z");
        assert_eq!(duration(0.0), "-");
        assert_eq!(duration(42.4), "42s");
        assert_eq!(duration(185.0), "3m05s");
        assert_eq!(duration(3720.0), "1h02m");
        let v = ListVersionsResponse {
            versions: vec![VersionInfo {
                version: "seed-abc".into(),
                trained_as: "source-1".into(),
                active: true,
                job_id: String::new(),
            }],
            activations: vec![ActivationEntry {
                category: "car".into(),
                version: "seed-abc".into(),
                actor: "seed".into(),
                ..Default::default()
            }],
        };
        assert_eq!(
            versions_lines(&v),
            [
                "VERSION   ACTIVE  TRAINED_AS  JOB",
                "seed-abc  yes     source-1    -",
                "",
                "GENERATION  VERSION   PREVIOUS  ACTOR  TIME  REASON",
                "0           seed-abc  -         seed   -     -",
            ]
        );
        assert_eq!(jobs_table(&[]), ["no jobs"]);
    }
}
