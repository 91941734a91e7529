//! The versions a session records: the socket protocol's (rigd's own is the package's).

/// The socket protocol's version: `v` on every line (docs/protocol.md).
pub const PROTOCOL_VERSION: u32 = 1;
