//! One client connection: read request lines (bounded), answer each, and forward events
//! after `subscribe`. A client that goes away only ends its connection, never a job.

use crate::daemon::protocol::{
    decode_request, encode, ErrorCode, ProtoError, Reply, ReplyBody, Request, ServerLine,
    SubscribeReply, MAX_LINE_BYTES,
};
use crate::daemon::Shared;
use crate::daemon::{commands, rig_commands};
use futures_util::StreamExt;
use std::sync::Arc;
use tokio::io::{AsyncRead, AsyncWriteExt};
use tokio::net::unix::OwnedReadHalf;
use tokio::net::UnixStream;
use tokio::sync::{broadcast, mpsc};
use tokio_util::codec::{FramedRead, LinesCodec, LinesCodecError};

/// Lines queued for a slow client before its events are dropped (it is told so).
const OUTBOX: usize = 1024;

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
/// either error `FramedRead` yields one `None` before it reads on (tokio issue 3976):
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
    let mut lines: Lines = FramedRead::new(rd, LinesCodec::new_with_max_length(MAX_LINE_BYTES));
    let mut after_error = false;
    let mut forwarders: Vec<tokio::task::JoinHandle<()>> = Vec::new();
    loop {
        let reply = match read_line(&mut lines, &mut after_error).await {
            LineRead::Eof => break,
            LineRead::Refused(e) => Reply::err(None, e),
            LineRead::Line(line) => {
                if line.trim().is_empty() {
                    continue;
                }
                match decode_request(line.as_bytes()) {
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
                        req if req.rig_action().is_some() => {
                            let (action, stage) = req.rig_action().expect("a rig request");
                            match rig_commands::request(&shared, action, stage).await {
                                Ok(body) => Reply::with(env.id, &body),
                                Err(e) => Reply::err(env.id, e),
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
    async fn an_over_long_last_line_without_a_newline_is_refused() {
        let got = read_all(&vec![b'x'; MAX_LINE_BYTES + 1]).await;
        assert_eq!(got.len(), 1, "{got:?}");
        assert!(matches!(&got[0], LineRead::Refused(e) if e.code == ErrorCode::LineTooLong));
    }
}
