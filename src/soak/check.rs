//! The soak's invariants, checked against the boards' own record of what their CNCs read, and
//! the history's and the audit trail's numbering.

use std::collections::{BTreeMap, HashMap};

use super::load::{Ledger, sha256_hex};
use super::rig::BoardRecord;
use crate::client::{Client, ClientError};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

/// What became of the jobs the clients got accepted.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub(crate) struct JobFigures {
    pub(crate) accepted: u64,
    pub(crate) resumes: u64,
    pub(crate) completed: u64,
    pub(crate) failed_with_offset: u64,
    pub(crate) cancelled: u64,
    /// Failed (the gateway could not confirm them) though the CNC read them whole: a kill -9
    /// between the last byte and the confirmation. Not a loss; a person resuming it sends the
    /// tail again.
    pub(crate) failed_yet_whole_on_board: u64,
    /// Accepted and never ended, or completed without the CNC having read the program whole.
    pub(crate) lost: u64,
    /// Programs the CNCs read whole more often than their jobs completed, jobs that ended
    /// twice, request ids that queued two jobs.
    pub(crate) twice: u64,
    /// Failed or cancelled jobs whose offset lies beyond their program.
    pub(crate) offsets_beyond_program: u64,
}

/// Checks every job of `ledger` against `boards`; returns the figures and a line for each
/// broken invariant.
pub(crate) fn jobs(ledger: &Ledger, boards: &BoardRecord) -> (JobFigures, Vec<String>) {
    let mut f = JobFigures::default();
    let mut broken = Vec::new();
    // Jobs by the SHA-256 of what their CNC reads: (completed, ended otherwise).
    let mut by_sha: HashMap<String, (u64, u64, Vec<&str>)> = HashMap::new();
    for (id, j) in &ledger.jobs {
        if j.resume_of.is_some() {
            f.resumes += 1;
        } else {
            f.accepted += 1;
        }
        let entry = by_sha.entry(sha256_hex(&j.bytes)).or_default();
        entry.2.push(id);
        if j.ended_again > 0 {
            f.twice += 1;
            broken.push(format!("job {id} on {} ended twice", j.machine));
        }
        let len = j.bytes.len() as u64;
        match j.last.as_ref().and_then(|e| e.kind.as_ref()) {
            Some(Kind::Completed(_)) => {
                f.completed += 1;
                entry.0 += 1;
            }
            Some(Kind::Failed(pb::job_event::Failed { byte_offset, .. }))
            | Some(Kind::Cancelled(pb::job_event::Cancelled { byte_offset, .. })) => {
                let (count, how) = match j.last.as_ref().and_then(|e| e.kind.as_ref()) {
                    Some(Kind::Cancelled(_)) => (&mut f.cancelled, "cancelled"),
                    _ => (&mut f.failed_with_offset, "failed"),
                };
                *count += 1;
                entry.1 += 1;
                if *byte_offset > len {
                    f.offsets_beyond_program += 1;
                    broken.push(format!(
                        "job {id} on {} {how} at {byte_offset} of a {len}-byte program",
                        j.machine
                    ));
                }
            }
            _ => {
                f.lost += 1;
                broken.push(format!(
                    "job {id} on {} never ended (last event: {:?})",
                    j.machine,
                    j.last.as_ref().and_then(|e| e.kind.as_ref())
                ));
            }
        }
    }
    for (sha, (completed, other, ids)) in &by_sha {
        let read = u64::from(boards.programs.get(sha).copied().unwrap_or(0));
        if read < *completed {
            f.lost += completed - read;
            broken.push(format!(
                "{} completed, its CNC read it whole {read} time(s): {}",
                completed,
                ids.join(", ")
            ));
        } else if read > *completed {
            let extra = read - completed;
            let conservative = extra.min(*other);
            f.failed_yet_whole_on_board += conservative;
            if extra > conservative {
                f.twice += extra - conservative;
                broken.push(format!(
                    "its CNC read {read} time(s) what {completed} completed job(s) sent: {}",
                    ids.join(", ")
                ));
            }
        }
    }
    for (request, first, second) in &ledger.duplicate_acceptances {
        f.twice += 1;
        broken.push(format!(
            "request {request} queued two jobs: {first} and {second}"
        ));
    }
    (f, broken)
}

/// The numbering of one log.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub(crate) struct SeqFigures {
    pub(crate) records: u64,
    pub(crate) first: u64,
    pub(crate) last: u64,
    /// Numbers missing between the first and the last.
    pub(crate) gaps: u64,
}

/// Every record number of the history (`audit`: the audit trail) of the last two days.
pub(crate) async fn records(
    client: &Client,
    audit: bool,
) -> Result<Vec<pb::HistoryRecord>, ClientError> {
    let mut out = Vec::new();
    let mut after: Option<u64> = None;
    loop {
        let mut params = vec![
            ("_time".to_string(), "[now(-2d)..]".to_string()),
            ("limit".to_string(), "10000".to_string()),
        ];
        if !audit {
            params.push((
                "kind".to_string(),
                "job,alarm,link,cnc,station,g05,tag,gateway,punch".to_string(),
            ));
        }
        if let Some(a) = after {
            params.push(("after".to_string(), a.to_string()));
        }
        let page = client.history(audit, &params).await?;
        out.extend(page.records);
        if !page.more {
            return Ok(out);
        }
        after = Some(page.next_after);
    }
}

pub(crate) fn numbering(records: &[pb::HistoryRecord]) -> SeqFigures {
    let mut seqs: Vec<u64> = records.iter().map(|r| r.seq).collect();
    seqs.sort_unstable();
    seqs.dedup();
    let (Some(&first), Some(&last)) = (seqs.first(), seqs.last()) else {
        return SeqFigures::default();
    };
    SeqFigures {
        records: seqs.len() as u64,
        first,
        last,
        gaps: (last - first + 1) - seqs.len() as u64,
    }
}

/// Accepted jobs whose submit the audit trail does not hold.
pub(crate) fn unaudited_submits(ledger: &Ledger, audit: &[pb::HistoryRecord]) -> Vec<String> {
    let audited: std::collections::HashSet<&str> = audit
        .iter()
        .filter_map(|r| match &r.record {
            Some(pb::history_record::Record::Audit(a)) if a.action == "job.submit" && a.ok => {
                Some(a.target.as_str())
            }
            _ => None,
        })
        .collect();
    let mut missing: Vec<String> = ledger
        .jobs
        .keys()
        .filter(|id| !audited.contains(id.as_str()))
        .cloned()
        .collect();
    missing.sort();
    missing
}

/// Lines of the gateway's log that tell a panic.
pub(crate) fn panics(log: &str) -> Vec<String> {
    log.lines()
        .filter(|l| l.contains("panicked at"))
        .map(str::to_string)
        .collect()
}

/// Counts by name.
pub(crate) fn counts<'a>(names: impl Iterator<Item = &'a str>) -> BTreeMap<String, u64> {
    let mut out = BTreeMap::new();
    for n in names {
        *out.entry(n.to_string()).or_default() += 1;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::soak::load::{JobEntry, program};

    fn event(job: &str, kind: Kind) -> pb::JobEvent {
        pb::JobEvent {
            job_id: job.to_string(),
            kind: Some(kind),
            ..Default::default()
        }
    }

    fn failed(offset: u64) -> Kind {
        Kind::Failed(pb::job_event::Failed {
            byte_offset: offset,
            ..Default::default()
        })
    }

    fn completed() -> Kind {
        Kind::Completed(pb::job_event::Completed::default())
    }

    /// A ledger of `jobs` (id, token, last event) and the board's record of `read` programs.
    fn run(jobs: &[(&str, &str, Option<Kind>)], read: &[(&str, u32)]) -> (JobFigures, Vec<String>) {
        let mut ledger = Ledger::default();
        let mut boards = BoardRecord::default();
        for (id, token, last) in jobs {
            let (bytes, header) = program(token, 1, 2000);
            ledger.jobs.insert(
                id.to_string(),
                JobEntry {
                    machine: "a-1".to_string(),
                    request_id: format!("r-{id}"),
                    bytes,
                    header,
                    resume_of: None,
                    last: last.clone().map(|k| event(id, k)),
                    ended_again: 0,
                    resumed: false,
                },
            );
        }
        for (token, n) in read {
            let (bytes, _) = program(token, 1, 2000);
            boards.programs.insert(sha256_hex(&bytes), *n);
        }
        super::jobs(&ledger, &boards)
    }

    #[test]
    fn a_completed_job_its_cnc_read_once_breaks_nothing() {
        let (f, broken) = run(&[("j1", "T1", Some(completed()))], &[("T1", 1)]);
        assert!(broken.is_empty(), "{broken:?}");
        assert_eq!((f.completed, f.lost, f.twice), (1, 0, 0));
    }

    #[test]
    fn a_completed_job_its_cnc_never_read_is_lost() {
        let (f, broken) = run(&[("j1", "T1", Some(completed()))], &[]);
        assert_eq!(f.lost, 1);
        assert_eq!(broken.len(), 1, "{broken:?}");
    }

    #[test]
    fn a_job_that_never_ended_is_lost() {
        let started = Kind::Started(pb::job_event::Started::default());
        let (f, broken) = run(&[("j1", "T1", Some(started)), ("j2", "T2", None)], &[]);
        assert_eq!(f.lost, 2);
        assert_eq!(broken.len(), 2, "{broken:?}");
    }

    #[test]
    fn a_program_read_twice_is_twice() {
        let (f, broken) = run(&[("j1", "T1", Some(completed()))], &[("T1", 2)]);
        assert_eq!(f.twice, 1);
        assert_eq!(broken.len(), 1, "{broken:?}");
    }

    #[test]
    fn a_failed_job_read_whole_is_counted_not_broken() {
        let (f, broken) = run(&[("j1", "T1", Some(failed(100)))], &[("T1", 1)]);
        assert!(broken.is_empty(), "{broken:?}");
        assert_eq!((f.failed_with_offset, f.failed_yet_whole_on_board), (1, 1));
    }

    #[test]
    fn an_offset_beyond_the_program_is_broken() {
        let (f, broken) = run(&[("j1", "T1", Some(failed(1_000_000)))], &[]);
        assert_eq!(f.offsets_beyond_program, 1);
        assert_eq!(broken.len(), 1, "{broken:?}");
    }

    #[test]
    fn a_request_id_that_queued_two_jobs_is_twice() {
        let mut ledger = Ledger::default();
        ledger
            .duplicate_acceptances
            .push(("r".to_string(), "j1".to_string(), "j2".to_string()));
        let (f, broken) = jobs(&ledger, &BoardRecord::default());
        assert_eq!(f.twice, 1);
        assert_eq!(broken.len(), 1);
    }

    #[test]
    fn numbering_counts_the_missing_numbers() {
        let records: Vec<pb::HistoryRecord> = [1u64, 2, 3, 5, 9]
            .iter()
            .map(|&seq| pb::HistoryRecord {
                seq,
                ..Default::default()
            })
            .collect();
        let n = numbering(&records);
        assert_eq!((n.first, n.last, n.records, n.gaps), (1, 9, 5, 4));
        assert_eq!(numbering(&[]).gaps, 0);
    }

    #[test]
    fn panics_are_found_in_the_log() {
        let log = "INFO started\nthread 'tokio-runtime-worker' panicked at src/x.rs:1:1:\nboom\n";
        assert_eq!(panics(log).len(), 1);
        assert!(panics("INFO all well\n").is_empty());
    }
}
