//! [`EngineError`]: why a relight, render or export could not be done, as a kind (which
//! the server maps to an HTTP status) and a message naming the field or the problem.

/// What kind of failure an [`EngineError`] is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    /// Well-formed, but a value breaks a rule (`lights[0].intensity[1] must be ...`).
    Invalid,
    /// A valid request this bundle or build cannot do (`solver "inverse"` without T).
    Unsupported,
    /// A bug: bad input never causes it.
    Internal,
    /// Stopped by its caller (the client went away, the server is stopping).
    Cancelled,
    /// Stopped at the request's limit of work (its time ran out).
    OverLimit,
}

/// A failure of the run-time transport; `message` names what and where.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EngineError {
    pub kind: ErrorKind,
    pub message: String,
}

impl EngineError {
    pub fn invalid(message: impl Into<String>) -> Self {
        Self {
            kind: ErrorKind::Invalid,
            message: message.into(),
        }
    }

    pub fn unsupported(message: impl Into<String>) -> Self {
        Self {
            kind: ErrorKind::Unsupported,
            message: message.into(),
        }
    }

    pub fn cancelled(message: impl Into<String>) -> Self {
        Self {
            kind: ErrorKind::Cancelled,
            message: message.into(),
        }
    }

    pub fn over_limit(message: impl Into<String>) -> Self {
        Self {
            kind: ErrorKind::OverLimit,
            message: message.into(),
        }
    }

    pub fn internal(message: impl Into<String>) -> Self {
        Self {
            kind: ErrorKind::Internal,
            message: message.into(),
        }
    }
}

impl std::fmt::Display for EngineError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for EngineError {}
