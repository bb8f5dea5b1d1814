//! The program library: list, read, store, check, adopt, revisions, compare, release, remove.

use prost::Message as _;

use super::{Client, ClientError, chunk_arg, no_reply, refusal, with_params};
use crate::bus::payload::encoding;
use cellgate_core::pb;
use cellgate_core::program::name::check_name;

impl Client {
    pub(crate) fn program_arg(name: &str) -> Result<(), ClientError> {
        check_name(name).map_err(ClientError::ProgramName)
    }

    /// Every program of the library, sorted by name.
    pub async fn program_list(&self) -> Result<Vec<pb::ProgramInfo>, ClientError> {
        let key = self.keys.any_program();
        let mut all: Vec<pb::ProgramInfo> = self
            .get_all("program library", &key, None, self.timeout)
            .await?
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(all)
    }

    /// One program's bytes.
    pub async fn program_get(&self, name: &str) -> Result<Vec<u8>, ClientError> {
        Self::program_arg(name)?;
        let key = self.keys.program(name);
        let what = format!("program {name}");
        let replies = self.get_raw(&what, &key, None, self.timeout).await?;
        match replies.into_iter().next() {
            Some(Ok((_, bytes, _))) => Ok(bytes),
            Some(Err((bytes, enc))) => Err(refusal(&what, &bytes, &enc)),
            None => Err(ClientError::NoAnswer {
                what,
                key,
                timeout: self.timeout,
            }),
        }
    }

    /// Stores a program in the library; answers it as stored, once it is on the gateway's
    /// disk (a get with a `ProgramWrite`).
    pub async fn program_put(
        &self,
        name: &str,
        program: &[u8],
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        if let Some(max) = self.admin["config"]["programs"]["max_size"].as_u64()
            && program.len() as u64 > max
        {
            return Err(ClientError::InvalidArgument {
                what: format!("program {name}"),
                reason: format!(
                    "{} bytes; the gateway's programs.max_size allows {max}",
                    program.len()
                ),
            });
        }
        self.program_put_with(name, program, String::new()).await
    }

    /// [`Self::program_put`] with a comment for the revision it makes.
    pub async fn program_put_with(
        &self,
        name: &str,
        program: &[u8],
        comment: String,
    ) -> Result<pb::ProgramInfo, ClientError> {
        self.program_store(name, program.to_vec(), comment).await
    }

    /// [`Self::program_put_with`], taking the program's bytes (no copy of them is made).
    pub async fn program_store(
        &self,
        name: &str,
        program: Vec<u8>,
        comment: String,
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Store(program)),
            comment,
        };
        self.program_write(name, "store", write).await
    }

    /// The gateway's `programs.max_inline` (from its admin document), else the default: the
    /// most a console takes in one upload.
    pub fn max_inline(&self) -> u64 {
        self.admin["config"]["programs"]["max_inline"]
            .as_u64()
            .unwrap_or(cellgate_core::config::ProgramsConfig::DEFAULT_MAX_INLINE)
    }

    /// Whether a store of `size` bytes as `name` would be taken (the name, the size, a lock,
    /// the quotas), before the bytes are sent: the program as it stands, or the refusal a
    /// store would get. Nothing is written.
    pub async fn program_check(
        &self,
        name: &str,
        size: u64,
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Check(pb::program_write::Check {
                size,
            })),
            comment: String::new(),
        };
        self.program_write(name, "check a store of", write).await
    }

    /// Stores `from`'s revision (empty: its latest) as `name`'s next revision (a punched
    /// program adopted as a revision of the library's program).
    pub async fn program_adopt(
        &self,
        name: &str,
        from: &str,
        revision: &str,
        comment: String,
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        Self::program_arg(from)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Adopt(pb::program_write::Adopt {
                from: from.to_string(),
                revision: revision.to_string(),
            })),
            comment,
        };
        self.program_write(name, "adopt into", write).await
    }

    /// Every kept revision of a program, newest first.
    pub async fn program_revisions(&self, name: &str) -> Result<pb::ProgramRevisions, ClientError> {
        Self::program_arg(name)?;
        let key = self.keys.program_revisions(name);
        self.get_one(&format!("revisions of {name}"), &key, None, self.timeout)
            .await
    }

    /// One revision's content.
    pub async fn program_revision(
        &self,
        name: &str,
        revision: &str,
    ) -> Result<Vec<u8>, ClientError> {
        Self::program_arg(name)?;
        chunk_arg("revision", revision)?;
        let key = self.keys.program_revision(name, revision);
        let what = format!("revision {revision} of {name}");
        let replies = self.get_raw(&what, &key, None, self.timeout).await?;
        match replies.into_iter().next() {
            Some(Ok((_, bytes, _))) => Ok(bytes),
            Some(Err((bytes, enc))) => Err(refusal(&what, &bytes, &enc)),
            None => Err(no_reply(&what, &key, self.timeout, self.timeout)),
        }
    }

    /// Two revisions compared (`a`, `b`: numbers or hashes; `None`: the defaults, the latest
    /// against the one before), ignoring `ignore` (`sequence,blanks,comments`).
    pub async fn program_diff(
        &self,
        name: &str,
        a: Option<&str>,
        b: Option<&str>,
        ignore: &[String],
    ) -> Result<pb::ProgramDiff, ClientError> {
        Self::program_arg(name)?;
        let mut params = Vec::new();
        if let Some(a) = a {
            params.push(("a".to_string(), a.to_string()));
        }
        if let Some(b) = b {
            params.push(("b".to_string(), b.to_string()));
        }
        if !ignore.is_empty() {
            params.push(("ignore".to_string(), ignore.join(",")));
        }
        let key = with_params(self.keys.program_diff(name), &params)?;
        self.get_one(&format!("diff of {name}"), &key, None, self.timeout)
            .await
    }

    /// Changes a revision's state (`revision` empty: the latest).
    pub async fn program_release(
        &self,
        name: &str,
        revision: &str,
        state: pb::RevisionState,
        comment: String,
    ) -> Result<pb::ProgramRevision, ClientError> {
        Self::program_arg(name)?;
        let key = self.keys.program_release(name);
        let release = pb::ProgramRelease {
            revision: revision.to_string(),
            state: state as i32,
            comment,
        };
        let payload = (release.encode_to_vec(), encoding::<pb::ProgramRelease>());
        self.get_one(
            &format!("release {name}"),
            &key,
            Some(payload),
            self.timeout,
        )
        .await
    }

    /// Removes a program from the library; answers it as it was, once it is gone.
    pub async fn program_remove(&self, name: &str) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Remove(pb::program_write::Remove {})),
            comment: String::new(),
        };
        self.program_write(name, "remove", write).await
    }
}
