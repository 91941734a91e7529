//! `resume_session`: capture the frames an interrupted or failed session is missing.

use crate::daemon::protocol::{ErrorCode, ProtoError, SubmitReply};
use crate::daemon::Shared;

pub fn submit(_shared: &Shared, name: &str) -> Result<SubmitReply, ProtoError> {
    Err(ProtoError::new(
        ErrorCode::Rejected,
        format!("cannot resume {name}: not built yet"),
    ))
}
