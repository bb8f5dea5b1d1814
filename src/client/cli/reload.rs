//! `cellgate reload`.

use clap::Args;

use super::{ClientCommand, ConnectArgs, Io};
use crate::client::{Client, ClientError, render};

/// `cellgate reload`: the gateway reads its cell file again and applies what changed.
#[derive(Debug, Clone, Args)]
pub struct ReloadArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Stop or restart the links of removed and changed machines at once: the job each is
    /// sending fails, saying a forced reload ended it. Without it, each link waits for its
    /// running job to end.
    #[arg(long)]
    pub force: bool,
    /// Print JSON: the gateway's ReloadResult (applied, generation, machines and PLCs added,
    /// removed, changed, settings, waiting), or, refused, {"applied": false, "code", "errors"}.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for ReloadArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    /// Exit 0 once the gateway took the file; 2, with every reason, when it refused it (it
    /// then goes on with the cell it had).
    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        match client.reload(self.force).await {
            Ok(r) => {
                if self.json {
                    let v = serde_json::to_value(&r).unwrap_or_default();
                    let _ = writeln!(io.out, "{v}");
                } else {
                    let _ = write!(io.out, "{}", render::reload_text(&r));
                }
                Ok(0)
            }
            Err(ClientError::Refused { code, message, .. }) => {
                let errors: Vec<&str> = message.lines().collect();
                if self.json {
                    let v = serde_json::json!({
                        "applied": false, "code": code.as_str_name(), "errors": errors,
                    });
                    let _ = writeln!(io.out, "{v}");
                }
                let _ = writeln!(
                    io.err,
                    "cellgate: reload refused ({}); the gateway goes on with the cell it had:",
                    code.as_str_name()
                );
                for e in errors {
                    let _ = writeln!(io.err, "  {e}");
                }
                Ok(2)
            }
            Err(e) => Err(e),
        }
    }
}
