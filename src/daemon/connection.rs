//! One client connection: read request lines (bounded), answer each, and forward events
//! after `subscribe`. A client that goes away only ends its connection, never a job. What
//! is queued for the client is bounded in bytes (`outbox`): a slow reader loses events (and
//! is told), one that reads nothing is disconnected.

use crate::daemon::accept::Permit;
use crate::daemon::commands;
use crate::daemon::events::Published;
use crate::daemon::outbox::{Line, Outbox};
use crate::daemon::protocol::{
    decode_request, encode, ErrorCode, ProtoError, Reply, ReplyBody, Request, ServerLine,
    SubscribeReply, MAX_LINE_BYTES,
};
use crate::daemon::{live_view, manual, rig_commands, Shared};
use futures_util::StreamExt;
use std::future::Future;
use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWriteExt};
use tokio::net::unix::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::UnixStream;
use tokio::sync::broadcast;
use tokio_util::codec::{FramedRead, LinesCodec, LinesCodecError};

/// Request lines, at most [`MAX_LINE_BYTES`] each (tokio-util's bounded `LinesCodec`).
type Lines = FramedRead<OwnedReadHalf, LinesCodec>;

/// What the reader got: a line (newline and `\r` stripped), one it refused with the reason
/// (the connection goes on with the next line), or the end of the connection.
#[derive(Debug)]
enum LineRead {
    Line(String),
    Refused(ProtoError),
    Eof,
}

/// The next request line. An over-long line is refused as soon as it passes the limit and
/// the codec then discards the rest of it; a line that is not UTF-8 is refused whole. After
/// either error `FramedRead` yields one `None` before it reads on (tokio-rs/tokio#3976):
/// `after_error` skips that one, so it is not taken for the end of the connection.
async fn read_line<R: AsyncRead + Unpin>(
    lines: &mut FramedRead<R, LinesCodec>,
    after_error: &mut bool,
) -> LineRead {
    loop {
        let next = lines.next().await;
        let was_error = std::mem::replace(after_error, false);
        let err = match next {
            Some(Ok(line)) => return LineRead::Line(line),
            None if was_error => continue,
            None => return LineRead::Eof,
            Some(Err(e)) => e,
        };
        *after_error = true;
        return match err {
            LinesCodecError::MaxLineLengthExceeded => LineRead::Refused(ProtoError::new(
                ErrorCode::LineTooLong,
                format!("line over the {MAX_LINE_BYTES}-byte limit"),
            )),
            LinesCodecError::Io(e) if e.kind() == std::io::ErrorKind::InvalidData => {
                LineRead::Refused(ProtoError::new(
                    ErrorCode::Malformed,
                    format!("not JSON: the line is not UTF-8 ({e})"),
                ))
            }
            // The socket itself failed: nothing more to read.
            LinesCodecError::Io(_) => LineRead::Eof,
        };
    }
}

/// `f`'s output, or `None` if `limit` passes first (no limit: it waits).
async fn within<F: Future>(limit: Option<Duration>, f: F) -> Option<F::Output> {
    match limit {
        Some(d) => tokio::time::timeout(d, f).await.ok(),
        None => Some(f.await),
    }
}

/// Subscriptions one connection may hold at once (each is a task and a place on the bus).
pub const MAX_SUBSCRIPTIONS: usize = 16;

/// The notice a client gets once it has caught up after losing events.
fn lost_notice(n: u64) -> Line {
    let note = Reply::err(
        None,
        ProtoError::new(
            ErrorCode::Internal,
            format!(
                "this client fell behind and lost {n} events (it read too slowly: its \
                 output queue is bounded)"
            ),
        ),
    );
    encode(&ServerLine::Reply(note)).into()
}

/// Serve one client until it leaves, stalls or idles out; `_permit` holds its place under
/// the connection limit until then.
pub async fn serve(stream: UnixStream, shared: Arc<Shared>, _permit: Permit) {
    let settings = &shared.settings;
    let stall = Duration::from_millis(settings.stalled_client_ms.max(1));
    let idle = (settings.idle_timeout_s > 0).then(|| Duration::from_secs(settings.idle_timeout_s));
    let (rd, wr) = stream.into_split();
    let outbox = Arc::new(Outbox::new(settings.output_queue_bytes, lost_notice));
    let mut writer = tokio::spawn(write_out(outbox.clone(), wr));
    let mut lines: Lines = FramedRead::new(rd, LinesCodec::new_with_max_length(MAX_LINE_BYTES));
    let mut after_error = false;
    let mut subs: Vec<tokio::task::JoinHandle<()>> = Vec::new();
    let mut preview: Option<live_view::client::Subscription> = None;
    loop {
        // Back-pressure: no request is read while the client's queue is full.
        if let Err(s) = outbox.wait_for_room(stall).await {
            tracing::warn!(
                queued_bytes = s.queued_bytes,
                "disconnecting a client that reads none of its replies: its queue stayed full \
                 for {} ms",
                stall.as_millis()
            );
            break;
        }
        subs.retain(|h| !h.is_finished());
        let read = read_line(&mut lines, &mut after_error);
        let idle_now = idle.filter(|_| subs.is_empty() && preview.is_none());
        let next = tokio::select! {
            next = within(idle_now, read) => next,
            () = outbox.given_up() => {
                tracing::warn!(
                    "disconnecting a client that reads none of its preview: its frame waited \
                     over {} ms",
                    stall.as_millis()
                );
                break;
            }
        };
        let Some(next) = next else {
            tracing::debug!("closing an idle connection");
            break;
        };
        let line = match next {
            LineRead::Eof => break,
            LineRead::Refused(e) => {
                outbox.reply(encode(&ServerLine::Reply(Reply::err(None, e))).into());
                continue;
            }
            LineRead::Line(line) if line.trim().is_empty() => continue,
            LineRead::Line(line) => line,
        };
        let handling = answer(&shared, &line, &outbox, &mut subs, &mut preview);
        match guarded(&line, handling).await {
            Ok(reply) => outbox.reply(encode(&ServerLine::Reply(reply)).into()),
            Err(reply) => {
                outbox.reply(encode(&ServerLine::Reply(reply)).into());
                break;
            }
        }
    }
    for f in subs {
        f.abort();
    }
    drop(preview);
    outbox.close();
    // What is queued goes out if the client takes it within the stall time.
    if tokio::time::timeout(stall, &mut writer).await.is_err() {
        writer.abort();
    }
}

/// The reply to one request line.
async fn answer(
    shared: &Arc<Shared>,
    line: &str,
    outbox: &Arc<Outbox>,
    subs: &mut Vec<tokio::task::JoinHandle<()>>,
    preview: &mut Option<live_view::client::Subscription>,
) -> Reply {
    let env = match decode_request(line.as_bytes()) {
        Err((id, e)) => return Reply::err(id, e),
        Ok(env) => env,
    };
    let id = env.id;
    let done = match env.request {
        Request::Subscribe { job_id } => return subscribe(shared, id, job_id, outbox, subs),
        r if live_view::client::handles(&r) => {
            live_view::client::handle(shared, r, outbox, preview).await
        }
        r if manual::is_manual(&r) => manual::handle(shared, r).await,
        r if r.rig_action().is_some() => {
            let (action, stage) = r.rig_action().expect("a rig request");
            rig_commands::request(shared, action, stage).await
        }
        r => commands::handle(shared, r),
    };
    match done {
        Ok(body) => Reply::with(id, &body),
        Err(e) => Reply::err(id, e),
    }
}

/// The reply `answer` gives, or, when it panics, an `internal` error naming the panic
/// (logged too) as `Err`: the connection is closed after it, the daemon goes on.
async fn guarded(line: &str, answer: impl Future<Output = Reply>) -> Result<Reply, Reply> {
    let mut answer = Box::pin(answer);
    // Each poll under catch_unwind: a panic anywhere in the handling is caught.
    let polled = std::future::poll_fn(move |cx| {
        match std::panic::catch_unwind(AssertUnwindSafe(|| answer.as_mut().poll(cx))) {
            Ok(std::task::Poll::Pending) => std::task::Poll::Pending,
            Ok(std::task::Poll::Ready(reply)) => std::task::Poll::Ready(Ok(reply)),
            Err(panic) => std::task::Poll::Ready(Err(panic)),
        }
    });
    polled.await.map_err(|panic| panicked(line, panic.as_ref()))
}

fn panicked(line: &str, panic: &(dyn std::any::Any + Send)) -> Reply {
    let what = crate::text::panic_message(panic);
    let id = serde_json::from_str::<serde_json::Value>(line)
        .ok()
        .and_then(|v| v.get("id").cloned());
    tracing::error!(panic = %what, "a request panicked: its connection is closed");
    Reply::err(
        id,
        ProtoError::new(
            ErrorCode::Internal,
            format!("the daemon failed on this request ({what}); the connection is closed"),
        ),
    )
}

/// Start a subscription (subscribed before the status is read: no event falls between).
fn subscribe(
    shared: &Shared,
    id: Option<serde_json::Value>,
    job_id: Option<u64>,
    outbox: &Arc<Outbox>,
    subs: &mut Vec<tokio::task::JoinHandle<()>>,
) -> Reply {
    if subs.len() >= MAX_SUBSCRIPTIONS {
        let e = ProtoError::new(
            ErrorCode::Unavailable,
            format!(
                "this connection already holds {MAX_SUBSCRIPTIONS} subscriptions, the most one may"
            ),
        );
        return Reply::err(id, e);
    }
    let rx = shared.events.subscribe();
    let status = match job_id.map(|j| commands::status(shared, j)).transpose() {
        Ok(s) => s,
        Err(e) => return Reply::err(id, e),
    };
    subs.push(tokio::spawn(forward(rx, job_id, outbox.clone())));
    Reply::with(
        id,
        &ReplyBody::Subscribe(SubscribeReply {
            subscribed: job_id,
            status,
        }),
    )
}

/// Write the queue to the client until it closes or the socket fails.
async fn write_out(outbox: Arc<Outbox>, mut wr: OwnedWriteHalf) {
    while let Some(line) = outbox.next().await {
        if wr.write_all(&line).await.is_err() {
            return;
        }
        drop(line);
        outbox.wrote();
    }
}

/// Copy events (of one job, or all) to the client's queue, never waiting for it.
async fn forward(mut rx: broadcast::Receiver<Published>, job_id: Option<u64>, out: Arc<Outbox>) {
    loop {
        match rx.recv().await {
            Ok(ev) => {
                if job_id.is_some_and(|id| id != ev.job_id) {
                    continue;
                }
                out.event(ev.line);
                if job_id.is_some() && ev.terminal {
                    return;
                }
            }
            Err(broadcast::error::RecvError::Lagged(n)) => {
                // The bus dropped them before this forwarder ran (rare: it never waits).
                out.reply(lost_notice(n));
            }
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    async fn read_all(input: &[u8]) -> Vec<LineRead> {
        // A small read buffer: the long line arrives over many reads, as from a socket.
        let r = tokio::io::BufReader::with_capacity(1000, input);
        let mut lines = FramedRead::new(r, LinesCodec::new_with_max_length(MAX_LINE_BYTES));
        let mut after_error = false;
        let mut got = Vec::new();
        loop {
            match read_line(&mut lines, &mut after_error).await {
                LineRead::Eof => return got,
                r => got.push(r),
            }
        }
    }

    #[tokio::test]
    async fn long_and_non_utf8_lines_are_refused_and_the_next_line_still_reads() {
        let mut input = vec![b'x'; MAX_LINE_BYTES + 10];
        input.extend_from_slice(b"\n{\"kind\":\"list\"}\r\n\xff\xfe\n");
        input.extend_from_slice(&[b'y'; MAX_LINE_BYTES]);
        input.extend_from_slice(b"\n");
        let got = read_all(&input).await;
        assert_eq!(got.len(), 4, "{got:?}");
        assert!(
            matches!(&got[0], LineRead::Refused(e) if e.code == ErrorCode::LineTooLong),
            "{:?}",
            got[0]
        );
        assert!(matches!(&got[1], LineRead::Line(l) if l == r#"{"kind":"list"}"#));
        assert!(
            matches!(&got[2], LineRead::Refused(e) if e.code == ErrorCode::Malformed && e.message.contains("UTF-8")),
            "{:?}",
            got[2]
        );
        // Exactly the limit is still a line.
        assert!(matches!(&got[3], LineRead::Line(l) if l.len() == MAX_LINE_BYTES));
    }

    #[tokio::test]
    async fn a_request_that_panics_is_answered_internal_with_its_id() {
        let line = r#"{"id": 7, "kind": "list"}"#;
        let ok = guarded(line, async {
            Reply::err(None, ProtoError::new(ErrorCode::Busy, "x"))
        });
        assert!(ok.await.is_ok());
        let boom = async {
            if line.len() > 1 {
                panic!("injected failure");
            }
            Reply::err(None, ProtoError::new(ErrorCode::Busy, "x"))
        };
        let reply = guarded(line, boom).await.unwrap_err();
        let v = serde_json::to_value(ServerLine::Reply(reply)).unwrap();
        assert_eq!(v["id"], 7, "{v}");
        assert_eq!(v["ok"], false, "{v}");
        assert_eq!(v["error"]["code"], "internal", "{v}");
        let msg = v["error"]["message"].as_str().unwrap();
        assert!(
            msg.contains("injected failure") && msg.contains("connection is closed"),
            "{msg}"
        );
    }

    #[tokio::test]
    async fn an_over_long_last_line_without_a_newline_is_refused() {
        let got = read_all(&vec![b'x'; MAX_LINE_BYTES + 1]).await;
        assert_eq!(got.len(), 1, "{got:?}");
        assert!(matches!(&got[0], LineRead::Refused(e) if e.code == ErrorCode::LineTooLong));
    }
}
