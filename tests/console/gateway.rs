//! A gateway running in this process, for the site's clients' tests: the embedded default
//! cell, its library, journal and history in a folder of the test's, its bus and the one
//! surface a test is about (the console, the MTConnect agent, the OPC UA server) on free
//! loopback ports, the others off unless the test's edit turns them on.

use crate::common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use cellgate::client::{Client, ConnectOptions};
use cellgate_core::config::{CellConfig, OpcuaConfig};
use common::bus::free_port;

/// The surface a gateway is started for: where [`Gateway::url`] points.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Surface {
    Console,
    Agent,
    Opcua,
}

/// A gateway of the embedded default cell running in this process until stopped.
pub(crate) struct Gateway {
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<Result<(), cellgate::gateway::GatewayError>>>,
    /// Where its surface answers: the console's or the agent's `http://…`, the OPC UA
    /// server's `opc.tcp://…/`.
    pub(crate) url: String,
    /// Its bus endpoint.
    pub(crate) endpoint: String,
    /// The agent's SHDR listener, where the cell file opens one.
    pub(crate) shdr: Option<String>,
    /// The folder of its library, journal and history (and the OPC UA server's PKI).
    pub(crate) dir: PathBuf,
    _dir: Option<tempfile::TempDir>,
}

impl Gateway {
    /// A gateway with its console, in a folder of its own.
    pub(crate) async fn start(edit: impl FnOnce(&mut CellConfig, &Path)) -> Gateway {
        Gateway::serving(Surface::Console, None, edit).await
    }

    /// A gateway with its console whose library, journal and history are in `dir`, kept
    /// after it stops.
    pub(crate) async fn start_in(dir: &Path, edit: impl FnOnce(&mut CellConfig, &Path)) -> Gateway {
        Gateway::serving(Surface::Console, Some(dir), edit).await
    }

    /// A gateway serving `surface`, in `dir` (or a folder of its own), edited by `edit`;
    /// returned once it serves what its cell file opens (at most a minute: a guard, not a
    /// time a test asserts).
    pub(crate) async fn serving(
        surface: Surface,
        dir: Option<&Path>,
        edit: impl FnOnce(&mut CellConfig, &Path),
    ) -> Gateway {
        let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
        let own = match dir {
            Some(_) => None,
            None => Some(tempfile::tempdir().unwrap()),
        };
        let dir = dir.map_or_else(
            || own.as_ref().unwrap().path().to_path_buf(),
            Path::to_path_buf,
        );
        let mut config = CellConfig::embedded_default();
        let (port, listener) = (free_port(), free_port());
        let listen = format!("127.0.0.1:{listener}");
        config.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
        config.programs.dir = dir.join("programs");
        match surface {
            Surface::Console => config.console.as_mut().unwrap().listen = listen,
            Surface::Agent => config.mtconnect.as_mut().unwrap().listen = listen,
            Surface::Opcua => {
                config.opcua = Some(OpcuaConfig {
                    listen,
                    pki_dir: Some(dir.join("pki")),
                    ..OpcuaConfig::default()
                })
            }
        }
        if surface != Surface::Console {
            config.console = None;
        }
        if surface != Surface::Agent {
            config.mtconnect = None;
        }
        if surface != Surface::Opcua {
            config.opcua = None;
        }
        edit(&mut config, &dir);
        let url = match surface {
            Surface::Opcua => format!("opc.tcp://127.0.0.1:{listener}/"),
            _ => format!("http://127.0.0.1:{listener}"),
        };
        let shdr = config
            .mtconnect
            .as_ref()
            .and_then(|m| m.shdr_listen.clone());
        let ready = Ready::of(&config);
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(cellgate::gateway::run(config, async {
            let _ = stopped.await;
        }));
        let endpoint = format!("tcp/127.0.0.1:{port}");
        ready.wait(&endpoint).await;
        Gateway {
            stop: Some(stop),
            task: Some(task),
            url,
            endpoint,
            shdr,
            dir,
            _dir: own,
        }
    }

    /// The OPC UA server's PKI folder.
    pub(crate) fn pki(&self) -> PathBuf {
        self.dir.join("pki")
    }

    /// A client of its cell.
    pub(crate) async fn client(&self) -> Client {
        Client::connect(&ConnectOptions {
            endpoint: self.endpoint.clone(),
            ..ConnectOptions::default()
        })
        .await
        .unwrap()
    }

    /// Stops it and waits for it to end cleanly.
    pub(crate) async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.task.take() {
            tokio::time::timeout(Duration::from_secs(20), t)
                .await
                .expect("the gateway stops")
                .unwrap()
                .unwrap();
        }
    }
}

/// What shows that a gateway serves: each listener its cell file opens answers.
struct Ready {
    console: Option<String>,
    agent: Option<String>,
    opcua: Option<String>,
}

impl Ready {
    fn of(config: &CellConfig) -> Ready {
        Ready {
            console: config.console.as_ref().map(|c| c.listen.clone()),
            agent: config.mtconnect.as_ref().map(|m| m.listen.clone()),
            opcua: config.opcua.as_ref().map(|o| o.listen.clone()),
        }
    }

    async fn wait(&self, endpoint: &str) {
        let http = reqwest::Client::new();
        let answers = |url: String| {
            let http = http.clone();
            async move { http.get(url).send().await.is_ok_and(|r| r.status() == 200) }
        };
        for _ in 0..600 {
            let mut up = true;
            if let Some(c) = &self.console {
                up &= answers(format!("http://{c}/health")).await;
            }
            if let Some(a) = &self.agent {
                up &= answers(format!("http://{a}/probe")).await;
            }
            if let Some(o) = &self.opcua {
                up &= tokio::net::TcpStream::connect(o.as_str()).await.is_ok();
            }
            if self.console.is_none() && self.agent.is_none() && self.opcua.is_none() {
                up = match Client::connect(&ConnectOptions {
                    endpoint: endpoint.to_string(),
                    ..ConnectOptions::default()
                })
                .await
                {
                    Ok(c) => {
                        c.close().await;
                        true
                    }
                    Err(_) => false,
                };
            }
            if up {
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!("the gateway on {endpoint} did not serve within a minute");
    }
}
