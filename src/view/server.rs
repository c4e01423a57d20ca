//! The viewer's web server: axum on a single-threaded tokio runtime for the page and the
//! WebSocket, and one render thread that owns the [`Scene`].
//!
//! Routes: `GET /` (the page), `/viewer.js`, `/viewer.css`, `/api/info` (the scene's
//! [`super::scene::Info`] as JSON), `/ws` (the frame socket; at most [`limits::CLIENTS`] at
//! once, more get HTTP 503).
//!
//! Per client, at most one request is being rendered and at most one waits: a newer request
//! replaces the waiting one (counted in [`super::protocol::FrameHeader::dropped`]), so the
//! page always gets the frame of the user's latest input next and never a backlog. Frames of
//! several clients are rendered in turn. A refused message gets an
//! [`super::protocol::ErrorReply`], is logged on stderr, and the connection stays open.

use std::net::{IpAddr, SocketAddr};
use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc;
use std::time::Instant;

use axum::Router;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio::sync::{Semaphore, oneshot};

use super::limits;
use super::protocol::{ErrorReply, FrameHeader, Request, pack};
use super::scene::{Info, Scene, SceneOptions};
use crate::error::{Error, Result};

const INDEX_HTML: &str = include_str!("page/index.html");
const VIEWER_JS: &str = include_str!("page/viewer.js");
const VIEWER_CSS: &str = include_str!("page/viewer.css");

/// Where the viewer listens and what it shows.
#[derive(Clone, Debug)]
pub struct ViewOptions {
    pub scene: SceneOptions,
    /// Address to bind (127.0.0.1 unless the user asks otherwise).
    pub host: IpAddr,
    /// Port; 0 picks a free one.
    pub port: u16,
    /// Stop on Ctrl-C / SIGINT (the command line); tests stop the viewer themselves.
    pub stop_on_ctrl_c: bool,
}

/// A rendered reply, or the refusal with the request's id.
type JobResult = std::result::Result<(FrameHeader, Vec<u8>), (u64, String)>;

struct Job {
    request: Request,
    reply: oneshot::Sender<JobResult>,
}

/// What every connection shares.
struct Shared {
    jobs: mpsc::Sender<Job>,
    info_json: String,
    num_expr: usize,
    clients: Arc<Semaphore>,
    next_client: AtomicU64,
}

impl Shared {
    fn submit(&self, request: Request) -> oneshot::Receiver<JobResult> {
        let (tx, rx) = oneshot::channel();
        // A closed channel (the render thread ended) drops `tx`: the receiver sees it.
        let _ = self.jobs.send(Job { request, reply: tx });
        rx
    }
}

/// A running viewer.
pub struct Viewer {
    addr: SocketAddr,
    info: Info,
    stop: Option<oneshot::Sender<()>>,
    server: Option<std::thread::JoinHandle<std::io::Result<()>>>,
}

impl Viewer {
    /// Loads the scene on its render thread, binds the address and starts serving; returns
    /// once the page can be fetched. Load and bind errors are returned here.
    pub fn start(opts: ViewOptions) -> Result<Viewer> {
        let (job_tx, job_rx) = mpsc::channel::<Job>();
        let (ready_tx, ready_rx) = mpsc::channel::<Result<Info>>();
        let scene_opts = opts.scene.clone();
        std::thread::Builder::new()
            .name("view-render".into())
            .spawn(move || render_thread(scene_opts, ready_tx, job_rx))
            .map_err(|e| Error::invalid("view", "render thread", e.to_string()))?;
        let info = ready_rx
            .recv()
            .map_err(|_| Error::invalid("view", "render thread", "ended while loading"))??;
        let what = format!("{}:{}", opts.host, opts.port);
        let listener = std::net::TcpListener::bind((opts.host, opts.port))
            .and_then(|l| l.set_nonblocking(true).map(|_| l))
            .map_err(|e| Error::invalid(&what, "--host/--port", e.to_string()))?;
        let addr = listener
            .local_addr()
            .map_err(|e| Error::invalid(&what, "--host/--port", e.to_string()))?;
        let shared = Arc::new(Shared {
            jobs: job_tx,
            info_json: serde_json::to_string(&info)
                .map_err(|e| Error::invalid("view", "info", e.to_string()))?,
            num_expr: info.expressions.len(),
            clients: Arc::new(Semaphore::new(limits::CLIENTS)),
            next_client: AtomicU64::new(1),
        });
        let (stop_tx, stop_rx) = oneshot::channel::<()>();
        let ctrl_c = opts.stop_on_ctrl_c;
        let server = std::thread::Builder::new()
            .name("view-server".into())
            .spawn(move || serve(listener, shared, stop_rx, ctrl_c))
            .map_err(|e| Error::invalid("view", "server thread", e.to_string()))?;
        Ok(Viewer {
            addr,
            info,
            stop: Some(stop_tx),
            server: Some(server),
        })
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The page's URL.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// What the page is told about the scene.
    pub fn info(&self) -> &Info {
        &self.info
    }

    /// Serves until the server ends (Ctrl-C with `stop_on_ctrl_c`).
    pub fn wait(mut self) -> Result<()> {
        self.join()
    }

    /// Stops serving (open connections are closed) and waits for the server thread.
    pub fn stop(mut self) -> Result<()> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        self.join()
    }

    fn join(&mut self) -> Result<()> {
        match self.server.take().map(|h| h.join()) {
            Some(Ok(r)) => r.map_err(|e| Error::invalid("view", "server", e.to_string())),
            Some(Err(_)) => Err(Error::invalid(
                "view",
                "server",
                "the server thread panicked",
            )),
            None => Ok(()),
        }
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
    }
}

/// The render thread: loads the scene, reports it ready, then answers jobs in turn until
/// every sender is gone. A panic while rendering one request is answered as an error.
fn render_thread(opts: SceneOptions, ready: mpsc::Sender<Result<Info>>, jobs: mpsc::Receiver<Job>) {
    let mut scene = match Scene::load(&opts) {
        Ok(s) => {
            let _ = ready.send(Ok(s.info().clone()));
            s
        }
        Err(e) => {
            let _ = ready.send(Err(e));
            return;
        }
    };
    for job in jobs {
        let id = job.request.id;
        let r = std::panic::catch_unwind(AssertUnwindSafe(|| scene.reply(&job.request)));
        let r = match r {
            Ok(Ok(reply)) => Ok(reply),
            Ok(Err(e)) => Err((id, e.to_string())),
            Err(_) => Err((
                id,
                "internal error while rendering (see the server log)".into(),
            )),
        };
        let _ = job.reply.send(r);
    }
}

fn serve(
    listener: std::net::TcpListener,
    shared: Arc<Shared>,
    stop: oneshot::Receiver<()>,
    ctrl_c: bool,
) -> std::io::Result<()> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::from_std(listener)?;
        let app = Router::new()
            .route(
                "/",
                get(|| async { page(INDEX_HTML, "text/html; charset=utf-8") }),
            )
            .route(
                "/viewer.js",
                get(|| async { page(VIEWER_JS, "text/javascript; charset=utf-8") }),
            )
            .route(
                "/viewer.css",
                get(|| async { page(VIEWER_CSS, "text/css; charset=utf-8") }),
            )
            .route("/api/info", get(info))
            .route("/ws", get(socket))
            .with_state(shared);
        let interrupted = async {
            if ctrl_c {
                let _ = tokio::signal::ctrl_c().await;
                eprintln!("view: interrupted, stopping");
            } else {
                std::future::pending::<()>().await;
            }
        };
        // Dropping the server future on stop closes every connection, WebSockets included.
        tokio::select! {
            r = axum::serve(listener, app) => r,
            _ = stop => Ok(()),
            _ = interrupted => Ok(()),
        }
    })
}

fn page(body: &'static str, mime: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, mime),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
        .into_response()
}

async fn info(State(s): State<Arc<Shared>>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "application/json"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        s.info_json.clone(),
    )
        .into_response()
}

async fn socket(State(s): State<Arc<Shared>>, ws: WebSocketUpgrade) -> Response {
    let Ok(permit) = s.clients.clone().try_acquire_owned() else {
        eprintln!("view: refused a viewer: {} are connected", limits::CLIENTS);
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("at most {} viewers at once", limits::CLIENTS),
        )
            .into_response();
    };
    let who = s.next_client.fetch_add(1, Ordering::Relaxed);
    ws.max_message_size(limits::SOCKET_MESSAGE_BYTES)
        .max_frame_size(limits::SOCKET_MESSAGE_BYTES)
        .on_upgrade(move |socket| async move {
            eprintln!("view: viewer {who} connected");
            client(socket, s, who).await;
            eprintln!("view: viewer {who} left");
            drop(permit);
        })
}

/// Counts a client's messages per second.
struct Rate {
    window: Instant,
    count: u32,
}

impl Rate {
    fn allow(&mut self) -> bool {
        if self.window.elapsed().as_secs_f64() >= 1.0 {
            self.window = Instant::now();
            self.count = 0;
        }
        self.count += 1;
        self.count <= limits::MESSAGES_PER_SECOND
    }
}

async fn wait(r: &mut Option<oneshot::Receiver<JobResult>>) -> Option<JobResult> {
    match r {
        Some(rx) => rx.await.ok(),
        None => std::future::pending().await,
    }
}

async fn refuse(socket: &mut WebSocket, who: u64, id: Option<u64>, why: &str) -> bool {
    eprintln!("view: viewer {who}: refused: {why}");
    let reply = serde_json::to_string(&ErrorReply::new(id, why)).unwrap_or_default();
    socket.send(Message::Text(reply.into())).await.is_ok()
}

/// One viewer's connection (see the module docs for the latest-wins rule).
async fn client(mut socket: WebSocket, s: Arc<Shared>, who: u64) {
    let mut pending: Option<Request> = None;
    let mut inflight: Option<oneshot::Receiver<JobResult>> = None;
    let mut dropped = 0u64;
    let mut rate = Rate {
        window: Instant::now(),
        count: 0,
    };
    loop {
        tokio::select! {
            msg = socket.recv() => {
                let text = match msg {
                    Some(Ok(Message::Text(t))) => t,
                    Some(Ok(Message::Binary(_))) => {
                        let why = "binary messages are not part of the protocol (send JSON text)";
                        if !refuse(&mut socket, who, None, why).await {
                            break;
                        }
                        continue;
                    }
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                    Some(Ok(Message::Close(_))) | None => break,
                    Some(Err(e)) => {
                        eprintln!("view: viewer {who}: {e}");
                        break;
                    }
                };
                if !rate.allow() {
                    let why = format!(
                        "more than {} messages in a second",
                        limits::MESSAGES_PER_SECOND
                    );
                    if !refuse(&mut socket, who, None, &why).await {
                        break;
                    }
                    continue;
                }
                match Request::parse(text.as_str(), s.num_expr) {
                    Err(r) => {
                        if !refuse(&mut socket, who, r.id, &r.why).await {
                            break;
                        }
                    }
                    Ok(req) if inflight.is_none() => inflight = Some(s.submit(req)),
                    Ok(req) => {
                        if pending.replace(req).is_some() {
                            dropped += 1;
                        }
                    }
                }
            }
            done = wait(&mut inflight) => {
                inflight = None;
                let sent = match done {
                    Some(Ok((mut header, payload))) => {
                        header.dropped = dropped;
                        let bytes = pack(&header, &[&payload]);
                        socket.send(Message::Binary(bytes.into())).await.is_ok()
                    }
                    Some(Err((id, why))) => refuse(&mut socket, who, Some(id), &why).await,
                    None => {
                        refuse(&mut socket, who, None, "the render thread has stopped").await;
                        false
                    }
                };
                if !sent {
                    break;
                }
                if let Some(r) = pending.take() {
                    inflight = Some(s.submit(r));
                }
            }
        }
    }
}
