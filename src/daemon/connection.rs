//! One client connection: read request lines (bounded), answer each, and forward events
//! after `subscribe`. A client that goes away only ends its connection, never a job.

use crate::daemon::commands;
use crate::daemon::protocol::{
    decode_request, encode, ErrorCode, ProtoError, Reply, ReplyBody, Request, ServerLine,
    SubscribeReply, MAX_LINE_BYTES,
};
use crate::daemon::Shared;
use std::sync::Arc;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::UnixStream;
use tokio::sync::{broadcast, mpsc};

/// Lines queued for a slow client before its events are dropped (it is told so).
const OUTBOX: usize = 1024;

enum LineRead {
    Line,
    /// A line over the limit, of this many bytes; it was skipped.
    TooLong(usize),
    Eof,
}

/// Read one line into `buf` (newline stripped), never holding more than the limit.
async fn read_line<R: tokio::io::AsyncBufRead + Unpin>(
    r: &mut R,
    buf: &mut Vec<u8>,
) -> std::io::Result<LineRead> {
    buf.clear();
    let mut seen = 0usize;
    loop {
        let avail = r.fill_buf().await?;
        if avail.is_empty() {
            return Ok(if seen == 0 {
                LineRead::Eof
            } else if seen > MAX_LINE_BYTES {
                LineRead::TooLong(seen)
            } else {
                LineRead::Line
            });
        }
        let (chunk, done) = match avail.iter().position(|&b| b == b'\n') {
            Some(i) => (&avail[..i], i + 1),
            None => (avail, avail.len()),
        };
        seen += chunk.len();
        if seen <= MAX_LINE_BYTES {
            buf.extend_from_slice(chunk);
        } else {
            buf.clear();
        }
        let newline = done > chunk.len();
        r.consume(done);
        if newline {
            return Ok(if seen > MAX_LINE_BYTES {
                LineRead::TooLong(seen)
            } else {
                LineRead::Line
            });
        }
    }
}

pub async fn serve(stream: UnixStream, shared: Arc<Shared>) {
    let (rd, mut wr) = stream.into_split();
    let (out_tx, mut out_rx) = mpsc::channel::<Vec<u8>>(OUTBOX);
    let writer = tokio::spawn(async move {
        while let Some(line) = out_rx.recv().await {
            if wr.write_all(&line).await.is_err() {
                break;
            }
        }
    });
    let mut reader = BufReader::new(rd);
    let mut buf = Vec::new();
    let mut forwarders: Vec<tokio::task::JoinHandle<()>> = Vec::new();
    loop {
        let read = match read_line(&mut reader, &mut buf).await {
            Ok(r) => r,
            Err(_) => break,
        };
        let reply = match read {
            LineRead::Eof => break,
            LineRead::TooLong(n) => Reply::err(
                None,
                ProtoError::new(
                    ErrorCode::LineTooLong,
                    format!("line of {n} bytes is over the {MAX_LINE_BYTES}-byte limit"),
                ),
            ),
            LineRead::Line => {
                let line = buf.strip_suffix(b"\r").unwrap_or(&buf);
                if line.iter().all(|b| b.is_ascii_whitespace()) {
                    continue;
                }
                match decode_request(line) {
                    Err((id, e)) => Reply::err(id, e),
                    Ok(env) => match env.request {
                        Request::Subscribe { job_id } => {
                            // Subscribe before reading the status: no event falls between.
                            let rx = shared.events.subscribe();
                            let status = job_id.map(|id| commands::status(&shared, id));
                            match status {
                                Some(Err(e)) => Reply::err(env.id, e),
                                st => {
                                    forwarders.push(tokio::spawn(forward(
                                        rx,
                                        job_id,
                                        out_tx.clone(),
                                    )));
                                    Reply::with(
                                        env.id,
                                        &ReplyBody::Subscribe(SubscribeReply {
                                            subscribed: job_id,
                                            status: st.and_then(|s| s.ok()),
                                        }),
                                    )
                                }
                            }
                        }
                        req => match commands::handle(&shared, req) {
                            Ok(body) => Reply::with(env.id, &body),
                            Err(e) => Reply::err(env.id, e),
                        },
                    },
                }
            }
        };
        if out_tx
            .send(encode(&ServerLine::Reply(reply)))
            .await
            .is_err()
        {
            break;
        }
    }
    for f in forwarders {
        f.abort();
    }
    drop(out_tx);
    let _ = writer.await;
}

/// Copy events (of one job, or all) to the client's outbox.
async fn forward(
    mut rx: broadcast::Receiver<crate::daemon::protocol::Event>,
    job_id: Option<u64>,
    out: mpsc::Sender<Vec<u8>>,
) {
    loop {
        match rx.recv().await {
            Ok(ev) => {
                if job_id.is_some_and(|id| id != ev.job_id) {
                    continue;
                }
                let terminal = job_id.is_some() && ev.body.is_terminal();
                if out.send(encode(&ServerLine::Event(ev))).await.is_err() {
                    return;
                }
                if terminal {
                    return;
                }
            }
            Err(broadcast::error::RecvError::Lagged(n)) => {
                let note = Reply::err(
                    None,
                    ProtoError::new(
                        ErrorCode::Internal,
                        format!("this subscriber fell behind and lost {n} events"),
                    ),
                );
                if out.send(encode(&ServerLine::Reply(note))).await.is_err() {
                    return;
                }
            }
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn long_lines_are_skipped_and_the_next_line_still_reads() {
        let mut input = vec![b'x'; MAX_LINE_BYTES + 10];
        input.extend_from_slice(b"\n{\"kind\":\"list\"}\n");
        let mut r = BufReader::with_capacity(1000, &input[..]);
        let mut buf = Vec::new();
        assert!(matches!(
            read_line(&mut r, &mut buf).await.unwrap(),
            LineRead::TooLong(n) if n == MAX_LINE_BYTES + 10
        ));
        assert!(matches!(
            read_line(&mut r, &mut buf).await.unwrap(),
            LineRead::Line
        ));
        assert_eq!(buf, br#"{"kind":"list"}"#);
        assert!(matches!(
            read_line(&mut r, &mut buf).await.unwrap(),
            LineRead::Eof
        ));
    }
}
