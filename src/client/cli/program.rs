//! `cellgate program`: the library from the command line.

use std::path::PathBuf;

use clap::Subcommand;

use super::{ClientCommand, ConnectArgs, Io, records};
use crate::client::{Client, ClientError, render};
use cellgate_core::pb;

/// `cellgate program`.
#[derive(Debug, Clone, Subcommand)]
pub enum ProgramCommand {
    /// Store a program file in the gateway's library under NAME (replacing one of that name).
    Put {
        #[command(flatten)]
        connect: ConnectArgs,
        /// Library name: 1-128 of A-Z a-z 0-9 . _ + -, starting with a letter or digit.
        name: String,
        /// The program file.
        file: PathBuf,
        /// A comment for the revision the store makes.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (a ProgramInfo) of the stored program.
        #[arg(long)]
        json: bool,
    },
    /// Fetch a program of the library: its latest revision, or with --revision another kept
    /// one (of a removed program too).
    Get {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's name in the library (`cellgate program ls` lists them).
        name: String,
        /// The revision: a number or a SHA-256 (or its first 8+ hex digits); `cellgate
        /// program history NAME` lists them. Default: the latest.
        #[arg(long, value_name = "REV")]
        revision: Option<String>,
        /// Write it to FILE instead of stdout (and say on stderr what was written).
        #[arg(short, long, value_name = "FILE")]
        output: Option<PathBuf>,
        /// Print JSON (name, revision, size, text) instead of the program's bytes.
        #[arg(long, conflicts_with = "output")]
        json: bool,
    },
    /// List the library.
    Ls {
        #[command(flatten)]
        connect: ConnectArgs,
        /// Print JSON (an array of name, size, modified_unix_ms).
        #[arg(long)]
        json: bool,
    },
    /// Remove a program from the library.
    Rm {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's name in the library.
        name: String,
        /// Print JSON (name, size, modified_unix_ms) of the removed program.
        #[arg(long)]
        json: bool,
    },
    /// A program's revisions, newest first: number, state, when, by whom, size, hash,
    /// comment.
    History {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// Print JSON (a ProgramRevisions).
        #[arg(long)]
        json: bool,
    },
    /// Compare two revisions block by block (default: the latest against the one before).
    /// Exit code 0 when they are the same, 1 when they differ.
    Diff {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// The older revision: a number or a SHA-256 (or its first 8+ hex digits).
        a: Option<String>,
        /// The newer revision (default: the latest).
        b: Option<String>,
        /// Leave out what does not change the machining: sequence, blanks, comments
        /// (repeat or comma-separate).
        #[arg(long, value_name = "WHAT", value_delimiter = ',')]
        ignore: Vec<String>,
        /// Print JSON (a ProgramDiff).
        #[arg(long)]
        json: bool,
    },
    /// Release a revision for production (default: the latest); with --state, set another
    /// state: draft unreleases (or unlocks a locked one). Needs program.release.
    Release {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// The revision (default: the latest).
        revision: Option<String>,
        /// The state it takes: released, locked or draft.
        #[arg(long, value_name = "STATE", default_value = "released")]
        state: String,
        /// Why, for the record.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (the ProgramRevision as it now is).
        #[arg(long)]
        json: bool,
    },
    /// Lock a revision (default: the latest): while the latest revision is locked nothing
    /// replaces or removes the program. Needs program.release.
    Lock {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// The revision (default: the latest).
        revision: Option<String>,
        /// Why, for the record.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (the ProgramRevision as it now is).
        #[arg(long)]
        json: bool,
    },
    /// Store another library program (a punched one) as NAME's next revision.
    Adopt {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program that gets the new revision (e.g. O1234).
        name: String,
        /// The library program to take the content of (e.g. the punched
        /// lathe-1-O1234-20261201T061500Z).
        from: String,
        /// Its revision (default: the latest).
        #[arg(long, value_name = "REV")]
        revision: Option<String>,
        /// A comment for the new revision.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (the ProgramInfo with its new revision).
        #[arg(long)]
        json: bool,
    },
}

impl ClientCommand for ProgramCommand {
    fn connect_args(&self) -> &ConnectArgs {
        match self {
            ProgramCommand::Put { connect, .. }
            | ProgramCommand::Get { connect, .. }
            | ProgramCommand::Ls { connect, .. }
            | ProgramCommand::Rm { connect, .. }
            | ProgramCommand::History { connect, .. }
            | ProgramCommand::Diff { connect, .. }
            | ProgramCommand::Release { connect, .. }
            | ProgramCommand::Lock { connect, .. }
            | ProgramCommand::Adopt { connect, .. } => connect,
        }
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        match self {
            ProgramCommand::Put {
                name,
                file,
                comment,
                json,
                ..
            } => put(client, io, name, file, comment.as_deref(), *json).await?,
            ProgramCommand::History { name, json, .. } => {
                return records::program_history(client, io, name, *json).await;
            }
            ProgramCommand::Diff {
                name,
                a,
                b,
                ignore,
                json,
                ..
            } => {
                return records::program_diff(
                    client,
                    io,
                    name,
                    a.as_deref(),
                    b.as_deref(),
                    ignore,
                    *json,
                )
                .await;
            }
            ProgramCommand::Release {
                name,
                revision,
                state,
                comment,
                json,
                ..
            } => {
                let state = match state.as_str() {
                    "released" => pb::RevisionState::Released,
                    "locked" => pb::RevisionState::Locked,
                    "draft" => pb::RevisionState::Draft,
                    other => {
                        return Err(ClientError::InvalidArgument {
                            what: format!("--state {other}"),
                            reason: "released, locked or draft".to_string(),
                        });
                    }
                };
                return records::program_state(
                    client,
                    io,
                    name,
                    revision.as_deref(),
                    state,
                    comment.as_deref(),
                    *json,
                )
                .await;
            }
            ProgramCommand::Lock {
                name,
                revision,
                comment,
                json,
                ..
            } => {
                return records::program_state(
                    client,
                    io,
                    name,
                    revision.as_deref(),
                    pb::RevisionState::Locked,
                    comment.as_deref(),
                    *json,
                )
                .await;
            }
            ProgramCommand::Adopt {
                name,
                from,
                revision,
                comment,
                json,
                ..
            } => {
                return records::program_adopt(
                    client,
                    io,
                    name,
                    from,
                    revision.as_deref(),
                    comment.as_deref(),
                    *json,
                )
                .await;
            }
            ProgramCommand::Get {
                name,
                revision,
                output,
                json,
                ..
            } => {
                get(
                    client,
                    io,
                    name,
                    revision.as_deref(),
                    output.as_ref(),
                    *json,
                )
                .await?
            }
            ProgramCommand::Ls { json, .. } => ls(client, io, *json).await?,
            ProgramCommand::Rm { name, json, .. } => {
                let info = client.program_remove(name).await?;
                if *json {
                    let _ = writeln!(io.out, "{}", render::program_json(&info));
                }
                let _ = writeln!(io.err, "{name}: removed");
            }
        }
        Ok(0)
    }
}

/// `program put`: the file stored as the program's next revision.
async fn put(
    client: &Client,
    io: &mut Io<'_>,
    name: &str,
    file: &std::path::Path,
    comment: Option<&str>,
    json: bool,
) -> Result<(), ClientError> {
    let data = crate::client::read_file(file).await?;
    let info = client
        .program_put_with(name, &data, comment.unwrap_or_default().to_string())
        .await?;
    if json {
        let _ = writeln!(io.out, "{}", render::program_json(&info));
    }
    let rev = info
        .latest
        .as_ref()
        .map(|r| format!(", revision {}", r.number))
        .unwrap_or_default();
    let _ = writeln!(
        io.err,
        "{}: stored, {}{rev}",
        info.name,
        render::bytes(info.size)
    );
    Ok(())
}

/// `program get`: a revision's text (default the latest), to standard output or a file.
/// The revisions are read first, so that what is printed names the revision it is, and a
/// removed program says so and how to read what is kept of it.
async fn get(
    client: &Client,
    io: &mut Io<'_>,
    name: &str,
    revision: Option<&str>,
    output: Option<&PathBuf>,
    json: bool,
) -> Result<(), ClientError> {
    let kept = client.program_revisions(name).await.map_err(|e| match e {
        ClientError::Refused { code, message, .. } => ClientError::Refused {
            what: format!("program {name}"),
            code,
            message,
        },
        e => e,
    })?;
    let number = match revision {
        Some(rev) => revision_number(&kept, rev),
        None => match kept.revisions.first() {
            Some(latest) if kept.removed => {
                return Err(ClientError::Refused {
                    what: format!("program {name}"),
                    code: pb::ErrorCode::NotFound,
                    message: format!(
                        "program {name:?} was removed (its latest revision was {n}); its {k} \
                         kept revision(s) can still be read: `cellgate program get {name} \
                         --revision {n}` (`cellgate program history {name}` lists them)",
                        n = latest.number,
                        k = kept.revisions.len()
                    ),
                });
            }
            Some(latest) => Some(latest.number),
            None => None,
        },
    };
    // By number where it is known: the bytes are that revision's even if a store comes
    // between the two requests.
    let asked = match (number, revision) {
        (Some(n), _) => n.to_string(),
        (None, Some(rev)) => rev.to_string(),
        (None, None) => String::new(),
    };
    let data = if asked.is_empty() {
        client.program_get(name).await?
    } else {
        client.program_revision(name, &asked).await?
    };
    if json {
        let v = serde_json::json!({
            "name": name,
            "revision": number,
            "size": data.len(),
            "text": String::from_utf8_lossy(&data),
        });
        let _ = writeln!(io.out, "{v}");
        return Ok(());
    }
    match output {
        Some(path) => {
            tokio::fs::write(path, &data)
                .await
                .map_err(|source| ClientError::File {
                    path: path.clone(),
                    op: "write",
                    source,
                })?;
            let rev = number
                .map(|n| format!(", revision {n}"))
                .unwrap_or_default();
            let _ = writeln!(
                io.err,
                "wrote {name} ({}{rev}) to {}",
                render::bytes(data.len() as u64),
                path.display()
            );
            Ok(())
        }
        None => {
            let _ = io.out.write_all(&data);
            Ok(())
        }
    }
}

/// The number of the kept revision `rev` names, as the gateway reads it (a number, `latest`,
/// or a SHA-256 or its first 8+ hex digits: the newest revision of that content), if one of
/// `kept` (newest first) is it; the gateway says why when none is.
fn revision_number(kept: &pb::ProgramRevisions, rev: &str) -> Option<u32> {
    let rev = rev.trim();
    if rev == "latest" {
        return kept.revisions.first().map(|r| r.number);
    }
    if let Ok(n) = rev.parse::<u32>()
        && rev.len() < 8
    {
        return kept.revisions.iter().any(|r| r.number == n).then_some(n);
    }
    let rev = rev.to_ascii_lowercase();
    let hits: Vec<&pb::ProgramRevision> = kept
        .revisions
        .iter()
        .filter(|r| rev.len() >= 8 && r.sha256.starts_with(&rev))
        .collect();
    match hits.first() {
        Some(newest) if hits.iter().all(|r| r.sha256 == newest.sha256) => Some(newest.number),
        _ => None,
    }
}

/// `program ls`: the library.
async fn ls(client: &Client, io: &mut Io<'_>, json: bool) -> Result<(), ClientError> {
    let list = client.program_list().await?;
    if json {
        let all: Vec<_> = list.iter().map(render::program_json).collect();
        let text = serde_json::to_string_pretty(&all).unwrap_or_default();
        let _ = writeln!(io.out, "{text}");
        return Ok(());
    }
    let _ = write!(io.out, "{}", render::program_table(&list));
    if list.is_empty() && client.admin().is_null() {
        // A gateway that hides @admin enforces roles: an empty answer may be a refusal.
        let _ = writeln!(
            io.err,
            "note: this gateway enforces roles; listing the library needs program.read"
        );
    }
    Ok(())
}
