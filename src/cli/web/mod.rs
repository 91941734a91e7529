//! `rigctl web`: the browser console. A gateway, not the daemon: a client of the daemon's
//! socket (as rigctl is) that serves one page over HTTP on loopback only, behind a random
//! token printed once as a URL (docs/console.md).
//!
//! One module per job: [`auth`] the token and host checks, [`link`] the daemon's socket,
//! [`routes`] the HTTP API, [`export`] the frames as an OME-TIFF download, [`bridge`] the page's WebSocket (events and the live view),
//! [`plots`] and [`offsets`] the charts as SVG, [`assets`] the embedded page.

pub mod assets;
pub mod auth;
pub mod bridge;
pub mod export;
pub mod link;
pub mod offsets;
pub mod plots;
pub mod routes;

use crate::cli::client::SocketArg;
use std::future::IntoFuture;
use std::io::Write;
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr};

#[derive(clap::Args, Debug)]
pub struct WebArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The port to serve on, on 127.0.0.1 and ::1 only (0: one the system picks; the URL
    /// printed says which). There is no option to listen beyond loopback: from another
    /// machine, use `ssh -L PORT:127.0.0.1:PORT rig-host` (docs/console.md).
    #[arg(long, value_name = "PORT", default_value_t = 0)]
    pub port: u16,
}

pub fn run(a: WebArgs) -> anyhow::Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(serve(a))
}

/// The loopback listeners: 127.0.0.1 on the port asked for, ::1 on the same port when the
/// machine has IPv6.
async fn listeners(port: u16) -> anyhow::Result<Vec<tokio::net::TcpListener>> {
    let v4 = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let first = tokio::net::TcpListener::bind(v4)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {v4}: {e}"))?;
    let port = first.local_addr()?.port();
    let mut all = vec![first];
    match tokio::net::TcpListener::bind(SocketAddr::from((Ipv6Addr::LOCALHOST, port))).await {
        Ok(l) => all.push(l),
        Err(e) => tracing::info!("not listening on [::1]:{port}: {e}"),
    }
    Ok(all)
}

async fn serve(a: WebArgs) -> anyhow::Result<()> {
    let token = auth::Token::random()?;
    let app = routes::App {
        daemon: link::Daemon {
            socket: a.socket.path(),
        },
        token: token.clone(),
    };
    let listeners = listeners(a.port).await?;
    let port = listeners[0].local_addr()?.port();
    let router = routes::router(app, token.clone());
    {
        let mut out = std::io::stdout().lock();
        writeln!(
            out,
            "rigctl web: the rig console at http://127.0.0.1:{port}/?token={}",
            token.as_str()
        )?;
        out.flush()?;
    }
    let mut tasks = tokio::task::JoinSet::new();
    for l in listeners {
        tasks.spawn(axum::serve(l, router.clone()).into_future());
    }
    while let Some(r) = tasks.join_next().await {
        r??;
    }
    Ok(())
}
