//! Access control for a shared server: bearer tokens with roles, hashed at rest.
//!
//! In: a tokens file (TOML, below) and each request's `Authorization: Bearer TOKEN` header
//! (or, for browsers opening a WebSocket, which cannot set headers, an `access_token` query
//! parameter on `GET`, as RFC 6750 §2.3 allows). Out: the request goes on with an
//! [`Identity`] (the token's name and role) in its extensions, or stops with
//! - `401 unauthorized` and `WWW-Authenticate: Bearer realm="translux"` when no token or an
//!   unknown token is presented on a protected route,
//! - `403 forbidden` when the token's role is below the route's ([`required_role`]),
//! - `429 rate_limited` with `Retry-After` when the token is over its request rate.
//!
//! ```toml
//! # tokens.toml — one [[tokens]] table per person or script
//! [[tokens]]
//! name = "alice"                # shown in logs and metrics, never secret
//! role = "editor"               # viewer < editor < admin
//! sha256 = "9f86d081884c7d65…"  # hex SHA-256 of the token (translux-server token hash)
//! rate = 50                     # optional: requests per second (default --rate-limit)
//! work_s = 30                   # optional: seconds of long work per request (default: the
//!                               # role's --viewer-work-s / --editor-work-s)
//! ```
//!
//! The file holds only SHA-256 hashes: tokens are long random strings
//! (`translux-server token add` makes 256-bit ones), so an unsalted fast hash is enough to keep
//! a leaked file from granting access, and a plain-text `token = ...` entry is refused. A
//! presented token is hashed and compared with every stored hash in constant time
//! ([`subtle`]), without stopping at the first match. Tokens are never logged: the request
//! log prints the path without its query, and no message here repeats a presented token.
//!
//! With no tokens configured the server is open to anyone who can reach it, so it binds to
//! loopback only ([`check_bind`]).

use std::collections::HashMap;
use std::fmt;
use std::io::{BufRead, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use axum::extract::{Request, State};
use axum::http::header::{AUTHORIZATION, RETRY_AFTER, WWW_AUTHENTICATE};
use axum::http::{HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use crate::error::AppError;

/// What a token may do; each role includes the ones below it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Read scenes, relight, render, stream.
    Viewer,
    /// Also upload scenes and run precompute jobs.
    Editor,
    /// Also unload and delete scenes.
    Admin,
}

impl Role {
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Editor => "editor",
            Role::Admin => "admin",
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Role {
    type Err = String;
    fn from_str(s: &str) -> Result<Role, String> {
        match s {
            "viewer" => Ok(Role::Viewer),
            "editor" => Ok(Role::Editor),
            "admin" => Ok(Role::Admin),
            _ => Err(format!(
                "unknown role {s:?}; the roles are viewer, editor, admin"
            )),
        }
    }
}

/// Who made a request: put into the request's extensions by [`middleware`] for every
/// request it lets through. `name` is the client key for per-client fairness and metrics.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    /// The token's name from the tokens file; [`LOCAL_NAME`] when no tokens are configured;
    /// [`ANONYMOUS_NAME`] on an open route without a (valid) token.
    pub name: Arc<str>,
    pub role: Option<Role>,
    /// The token's own work limit (`None`: its role's; see `ServerParams::work_limit`).
    pub work: Option<Duration>,
}

/// The role of a request by the identity the access check gave it; a router without the
/// check in front of it (an embedding library, tests) acts for its only user, an admin.
pub fn role_of(identity: &Option<axum::Extension<Identity>>) -> Option<Role> {
    match identity {
        Some(axum::Extension(i)) => i.role,
        None => Some(Role::Admin),
    }
}

/// The identity of every request when no tokens are configured (loopback only).
pub const LOCAL_NAME: &str = "local";
/// The identity of a request without a valid token on an open route.
pub const ANONYMOUS_NAME: &str = "anonymous";

/// One entry of the tokens file, as read.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TokenEntry {
    name: String,
    role: Role,
    sha256: String,
    #[serde(default)]
    rate: Option<f64>,
    #[serde(default)]
    work_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TokensFile {
    #[serde(default)]
    tokens: Vec<toml::Table>,
}

/// A configured token: its name, role, hash and rate.
#[derive(Clone)]
struct Token {
    name: Arc<str>,
    role: Role,
    hash: [u8; 32],
    /// Requests per second (`None`: the default rate).
    rate: Option<f64>,
    /// The most time one request's long work may take (`None`: the role's limit).
    work: Option<Duration>,
}

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // The hash is not the token, but there is no reason to print it either.
        f.debug_struct("Token")
            .field("name", &self.name)
            .field("role", &self.role)
            .field("rate", &self.rate)
            .finish_non_exhaustive()
    }
}

/// Rate-limit settings: a token bucket per token, refilled at `per_second` up to `burst`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateLimit {
    pub per_second: f64,
    pub burst: f64,
}

impl Default for RateLimit {
    fn default() -> Self {
        RateLimit {
            per_second: 50.0,
            burst: 100.0,
        }
    }
}

/// The access rules of one server: its tokens (possibly none) and rate limits.
#[derive(Debug)]
pub struct Auth {
    /// Swapped whole when the tokens file changes ([`Auth::reload_if_changed`]).
    tokens: RwLock<Arc<Vec<Token>>>,
    rate: RateLimit,
    buckets: Mutex<HashMap<Arc<str>, Bucket>>,
    /// The tokens file the tokens were read from, if any.
    source: Option<TokensSource>,
}

/// A tokens file and what it was (inode, size, modification time) when last read.
#[derive(Debug)]
struct TokensSource {
    path: PathBuf,
    seen: Mutex<Option<FileStamp>>,
}

/// A file's inode, size and modification time: a rewrite (renamed into place) or an
/// append changes it.
type FileStamp = (u64, u64, Option<std::time::SystemTime>);

fn file_stamp(path: &Path) -> Option<FileStamp> {
    let m = std::fs::metadata(path).ok()?;
    #[cfg(unix)]
    let ino = std::os::unix::fs::MetadataExt::ino(&m);
    #[cfg(not(unix))]
    let ino = 0;
    Some((ino, m.len(), m.modified().ok()))
}

#[derive(Debug, Clone, Copy)]
struct Bucket {
    level: f64,
    at: Instant,
}

/// Why a presented token was not accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Denied {
    /// No token on a protected route.
    Missing,
    /// A token that matches no entry.
    Unknown,
    /// A known token whose role is below the route's.
    Forbidden { has: Role, needs: Role },
}

impl Auth {
    /// No tokens: every request is allowed (and the server must bind to loopback).
    pub fn open() -> Auth {
        Auth::with_tokens(Vec::new(), RateLimit::default())
    }

    fn with_tokens(tokens: Vec<Token>, rate: RateLimit) -> Auth {
        Auth {
            tokens: RwLock::new(Arc::new(tokens)),
            rate,
            buckets: Mutex::new(HashMap::new()),
            source: None,
        }
    }

    /// Reads a tokens file (see the module documentation). Errors name the file and the
    /// entry. The file is remembered: [`Auth::reload_if_changed`] reads it again.
    pub fn from_file(path: &Path, rate: RateLimit) -> anyhow::Result<Auth> {
        // The stamp before the text: a change while reading is seen at the next look.
        let stamp = file_stamp(path);
        let mut auth = Auth::read_file(path, rate)?;
        auth.source = Some(TokensSource {
            path: path.to_path_buf(),
            seen: Mutex::new(stamp),
        });
        Ok(auth)
    }

    fn read_file(path: &Path, rate: RateLimit) -> anyhow::Result<Auth> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the tokens file {}", path.display()))?;
        Auth::from_toml(&text, rate).with_context(|| format!("tokens file {}", path.display()))
    }

    /// Reads the tokens file again if it changed since it was last read (servers sharing
    /// a tokens file see a `token add` made on any of them): `None` when it did not change
    /// (or there is no file), the new [`Auth::summary`] when the new tokens are in force,
    /// the error when the file does not read — the tokens in force are then kept, and the
    /// file is read again when it changes again.
    pub fn reload_if_changed(&self) -> Option<anyhow::Result<String>> {
        let source = self.source.as_ref()?;
        let stamp = file_stamp(&source.path);
        {
            let mut seen = source.seen.lock().unwrap_or_else(|e| e.into_inner());
            if *seen == stamp {
                return None;
            }
            *seen = stamp;
        }
        Some(Auth::read_file(&source.path, self.rate).map(|fresh| {
            let tokens = fresh.tokens();
            *self.tokens.write().unwrap_or_else(|e| e.into_inner()) = tokens;
            self.summary()
        }))
    }

    /// The tokens in force.
    fn tokens(&self) -> Arc<Vec<Token>> {
        self.tokens
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Parses the tokens file's text.
    pub fn from_toml(text: &str, rate: RateLimit) -> anyhow::Result<Auth> {
        check_rate(rate.per_second, "the default rate")?;
        if !(rate.burst.is_finite() && rate.burst >= 1.0) {
            bail!(
                "the rate-limit burst must be finite and >= 1, got {}",
                rate.burst
            );
        }
        let file: TokensFile = toml::from_str(text).map_err(|e| {
            // toml's message quotes the offending line, which may hold a hash; keep only the
            // description and the position.
            let pos = e.span().map(|s| line_of(text, s.start)).unwrap_or(0);
            anyhow::anyhow!("line {pos}: {}", e.message())
        })?;
        let mut tokens: Vec<Token> = Vec::new();
        for (k, table) in file.tokens.into_iter().enumerate() {
            let at = format!("tokens[{k}]");
            if table.contains_key("token") {
                bail!(
                    "{at} holds a plain-text `token`; the file stores only hashes: put \
                     `sha256 = \"…\"` from `translux-server token hash` instead"
                );
            }
            let entry: TokenEntry = table
                .try_into()
                .map_err(|e: toml::de::Error| anyhow::anyhow!("{at}: {}", e.message()))?;
            check_name(&entry.name).map_err(|e| anyhow::anyhow!("{at}.name: {e}"))?;
            let hash =
                parse_hash(&entry.sha256).map_err(|e| anyhow::anyhow!("{at}.sha256: {e}"))?;
            if let Some(r) = entry.rate {
                check_rate(r, &format!("{at}.rate"))?;
            }
            let work = entry
                .work_s
                .map(|s| check_work(s, &format!("{at}.work_s")))
                .transpose()?;
            if let Some(other) = tokens.iter().find(|t| *t.name == *entry.name) {
                bail!("{at}.name: {:?} is used twice", other.name);
            }
            if let Some(other) = tokens.iter().find(|t| t.hash == hash) {
                bail!(
                    "{at}.sha256: the same token hash as {:?}; give every token its own value",
                    other.name
                );
            }
            tokens.push(Token {
                name: entry.name.into(),
                role: entry.role,
                hash,
                rate: entry.rate,
                work,
            });
        }
        if tokens.is_empty() {
            bail!("no [[tokens]] entries; add one with `translux-server token add`");
        }
        Ok(Auth::with_tokens(tokens, rate))
    }

    /// Whether any token is configured (otherwise every request is allowed).
    pub fn enabled(&self) -> bool {
        !self.tokens().is_empty()
    }

    /// The number of tokens per role, for the start-up log line.
    pub fn summary(&self) -> String {
        let tokens = self.tokens();
        let count = |r: Role| tokens.iter().filter(|t| t.role == r).count();
        format!(
            "{} tokens ({} admin, {} editor, {} viewer)",
            tokens.len(),
            count(Role::Admin),
            count(Role::Editor),
            count(Role::Viewer)
        )
    }

    /// The token that hashes to the same value as `presented`, compared in constant time
    /// against every entry.
    fn lookup(&self, presented: &str) -> Option<Token> {
        let hash = sha256(presented.as_bytes());
        let mut found = None;
        for t in self.tokens().iter() {
            if bool::from(t.hash.ct_eq(&hash)) {
                found = Some(t.clone());
            }
        }
        found
    }

    /// Decides a request for a route that needs `needs` (`None`: open) with the presented
    /// token, if any.
    pub fn check(&self, presented: Option<&str>, needs: Option<Role>) -> Result<Identity, Denied> {
        if !self.enabled() {
            return Ok(Identity {
                name: LOCAL_NAME.into(),
                role: Some(Role::Admin),
                work: None,
            });
        }
        let token = presented.and_then(|p| self.lookup(p));
        let Some(needs) = needs else {
            return Ok(match token {
                Some(t) => Identity {
                    name: t.name.clone(),
                    role: Some(t.role),
                    work: t.work,
                },
                None => Identity {
                    name: ANONYMOUS_NAME.into(),
                    role: None,
                    work: None,
                },
            });
        };
        match (presented, token) {
            (None, _) => Err(Denied::Missing),
            (Some(_), None) => Err(Denied::Unknown),
            (Some(_), Some(t)) if t.role < needs => Err(Denied::Forbidden { has: t.role, needs }),
            (Some(_), Some(t)) => Ok(Identity {
                name: t.name.clone(),
                role: Some(t.role),
                work: t.work,
            }),
        }
    }

    /// Takes one request from `name`'s bucket; `Err(seconds)` to wait when it is empty.
    pub fn take(&self, name: &Arc<str>) -> Result<(), f64> {
        let per_second = self
            .tokens()
            .iter()
            .find(|t| t.name == *name)
            .and_then(|t| t.rate)
            .unwrap_or(self.rate.per_second);
        let burst = self.rate.burst.max(per_second);
        let now = Instant::now();
        let Ok(mut buckets) = self.buckets.lock() else {
            return Ok(());
        };
        let b = buckets.entry(name.clone()).or_insert(Bucket {
            level: burst,
            at: now,
        });
        b.level = (b.level + now.duration_since(b.at).as_secs_f64() * per_second).min(burst);
        b.at = now;
        if b.level >= 1.0 {
            b.level -= 1.0;
            Ok(())
        } else {
            Err((1.0 - b.level) / per_second)
        }
    }
}

/// The role a route needs, `None` for the open ones: everything outside `/api/` (the
/// viewer's files, `/healthz`, `/metrics`). Under `/api/`: uploads (`POST /api/v1/scenes`)
/// and jobs need editor, `DELETE /api/v1/scenes/{id}` admin, everything else viewer —
/// including paths no route serves, so that an unauthenticated client learns nothing.
pub fn required_role(method: &Method, path: &str) -> Option<Role> {
    let rest = path.strip_prefix("/api")?;
    if !(rest.is_empty() || rest.starts_with('/')) {
        return None;
    }
    let segments: Vec<&str> = rest.split('/').filter(|s| !s.is_empty()).collect();
    Some(match segments.as_slice() {
        ["v1", "scenes"] if method == Method::POST => Role::Editor,
        ["v1", "scenes", _, "resimulate"] => Role::Editor,
        ["v1", "scenes", _] if method == Method::DELETE => Role::Admin,
        ["v1", "jobs", ..] => Role::Editor,
        _ => Role::Viewer,
    })
}

/// The token a request presents: `Authorization: Bearer TOKEN`, else (on `GET` only) the
/// `access_token` query parameter. A malformed `Authorization` header counts as a token that
/// matches nothing.
fn presented_token(req: &Request) -> Option<String> {
    if let Some(v) = req.headers().get(AUTHORIZATION) {
        let v = v.to_str().unwrap_or("");
        return Some(match v.split_once(' ') {
            Some((scheme, t)) if scheme.eq_ignore_ascii_case("bearer") => t.trim().to_string(),
            _ => String::new(),
        });
    }
    if req.method() != Method::GET {
        return None;
    }
    let query = req.uri().query()?;
    query.split('&').find_map(|kv| {
        let (k, v) = kv.split_once('=')?;
        (k == "access_token").then(|| percent_decode(v))
    })
}

/// `%XX` and `+` decoding for one query value (tokens are URL-safe; this only undoes what a
/// browser's `URLSearchParams` might have done).
fn percent_decode(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut k = 0;
    while k < bytes.len() {
        match bytes[k] {
            b'%' if k + 2 < bytes.len() => {
                let hex = |b: u8| (b as char).to_digit(16);
                match (hex(bytes[k + 1]), hex(bytes[k + 2])) {
                    (Some(hi), Some(lo)) => {
                        out.push((hi * 16 + lo) as u8);
                        k += 3;
                        continue;
                    }
                    _ => out.push(b'%'),
                }
            }
            b'+' => out.push(b' '),
            b => out.push(b),
        }
        k += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The axum middleware: decides every request with [`Auth::check`] and the token bucket,
/// and puts the [`Identity`] into the request's extensions.
pub async fn middleware(State(auth): State<Arc<Auth>>, mut req: Request, next: Next) -> Response {
    let needs = required_role(req.method(), req.uri().path());
    let presented = presented_token(&req);
    match auth.check(presented.as_deref(), needs) {
        Ok(identity) => {
            if auth.enabled()
                && needs.is_some()
                && let Err(wait) = auth.take(&identity.name)
            {
                let secs = wait.ceil().max(1.0) as u64;
                let mut r = AppError::new(
                    StatusCode::TOO_MANY_REQUESTS,
                    "rate_limited",
                    format!(
                        "token {:?} is over its rate limit; retry in {secs} s",
                        identity.name
                    ),
                )
                .into_response();
                r.headers_mut().insert(RETRY_AFTER, HeaderValue::from(secs));
                return r;
            }
            req.extensions_mut().insert(identity);
            next.run(req).await
        }
        Err(denied) => denied_response(denied),
    }
}

fn denied_response(denied: Denied) -> Response {
    let (status, code, message, challenge) = match denied {
        Denied::Missing => (
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "this route needs a token: send `Authorization: Bearer TOKEN`".to_string(),
            "Bearer realm=\"translux\"",
        ),
        Denied::Unknown => (
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "the token is not known to this server".to_string(),
            "Bearer realm=\"translux\", error=\"invalid_token\"",
        ),
        Denied::Forbidden { has, needs } => (
            StatusCode::FORBIDDEN,
            "forbidden",
            format!("this route needs the {needs} role; the token has {has}"),
            "Bearer realm=\"translux\", error=\"insufficient_scope\"",
        ),
    };
    let mut r = AppError::new(status, code, message).into_response();
    r.headers_mut()
        .insert(WWW_AUTHENTICATE, HeaderValue::from_static(challenge));
    r
}

/// Refuses to listen beyond loopback without tokens: an open server on a network would let
/// anyone upload and delete scenes.
pub fn check_bind(addr: &SocketAddr, auth: &Auth) -> anyhow::Result<()> {
    if !auth.enabled() && !addr.ip().is_loopback() {
        bail!(
            "refusing to listen on {addr} without access control: with no tokens configured \
             the server binds to loopback only (127.0.0.1 or ::1); give it a tokens file with \
             --tokens FILE (see `translux-server token add`) to serve a network"
        );
    }
    Ok(())
}

/// SHA-256 of `bytes`.
pub fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
}

/// Lower-case hex.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn parse_hash(s: &str) -> Result<[u8; 32], String> {
    let s = s.trim();
    if s.len() != 64 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(format!(
            "must be 64 hex digits (a SHA-256 from `translux-server token hash`), got {} characters",
            s.len()
        ));
    }
    let mut out = [0u8; 32];
    for (k, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(&s[2 * k..2 * k + 2], 16).map_err(|e| e.to_string())?;
    }
    Ok(out)
}

fn check_name(name: &str) -> Result<(), String> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.' | b'@'));
    if ok {
        Ok(())
    } else {
        Err(format!(
            "{name:?} must be 1 to 64 letters, digits, '-', '_', '.' or '@'"
        ))
    }
}

fn check_rate(r: f64, what: &str) -> anyhow::Result<()> {
    if !(r.is_finite() && r > 0.0) {
        bail!("{what} must be a finite number of requests per second > 0, got {r}");
    }
    Ok(())
}

/// A token's `work_s`: seconds above 0, at most a year (as `--editor-work-s`).
fn check_work(s: f64, what: &str) -> anyhow::Result<Duration> {
    if !(s.is_finite() && s > 0.0 && s <= 365.0 * 86_400.0) {
        bail!("{what} must be a number of seconds above 0 (at most a year), got {s}");
    }
    Ok(Duration::from_secs_f64(s))
}

fn line_of(text: &str, byte: usize) -> usize {
    text.get(..byte).map_or(0, |t| t.matches('\n').count()) + 1
}

/// Shortest token `token hash` accepts: a short token's SHA-256 can be reversed by search.
pub const MIN_TOKEN_LEN: usize = 24;

/// `translux-server token ...`: make and hash tokens.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum TokenCommand {
    /// Make a new random token, append its hash to the tokens file (created if absent), and
    /// print the token once on standard output.
    Add {
        /// The tokens file.
        #[arg(long, value_name = "FILE")]
        tokens: PathBuf,
        /// The token's name (shown in logs and metrics).
        #[arg(long)]
        name: String,
        /// viewer, editor or admin.
        #[arg(long)]
        role: Role,
        /// Requests per second for this token (default: the server's --rate-limit).
        #[arg(long)]
        rate: Option<f64>,
    },
    /// Read a token from standard input (one line) and print its SHA-256 for the tokens file.
    Hash,
}

/// Runs a [`TokenCommand`], writing the answer to `out`.
pub fn token_command(cmd: &TokenCommand, out: &mut dyn Write) -> anyhow::Result<()> {
    match cmd {
        TokenCommand::Hash => {
            let mut line = String::new();
            std::io::stdin()
                .lock()
                .read_line(&mut line)
                .context("cannot read the token from standard input")?;
            writeln!(out, "{}", hash_token(line.trim_end_matches(['\r', '\n']))?)?;
            Ok(())
        }
        TokenCommand::Add {
            tokens,
            name,
            role,
            rate,
        } => {
            let token = new_token()?;
            add_token(tokens, name, *role, *rate, &token)?;
            writeln!(out, "{token}")?;
            eprintln!(
                "added {name:?} ({role}) to {}; the token above is shown only now",
                tokens.display()
            );
            Ok(())
        }
    }
}

/// The SHA-256 hex of `token` for the tokens file; refuses short tokens.
pub fn hash_token(token: &str) -> anyhow::Result<String> {
    if token.chars().count() < MIN_TOKEN_LEN {
        bail!(
            "the token has {} characters; use at least {MIN_TOKEN_LEN} random ones (or \
             `translux-server token add`): a short token's hash can be reversed by search",
            token.chars().count()
        );
    }
    Ok(hex(&sha256(token.as_bytes())))
}

/// A new 256-bit random token: `tlx_` and 64 hex digits.
pub fn new_token() -> anyhow::Result<String> {
    let mut bytes = [0u8; 32];
    getrandom::fill(&mut bytes).map_err(|e| anyhow::anyhow!("no randomness: {e}"))?;
    Ok(format!("tlx_{}", hex(&bytes)))
}

/// Appends an entry for `token` to the tokens file, after checking that the result still
/// reads (no duplicate name). The file is locked meanwhile, so that two `token add` at
/// once (servers sharing the file) cannot both pass the check and add one name twice.
pub fn add_token(
    file: &Path,
    name: &str,
    role: Role,
    rate: Option<f64>,
    token: &str,
) -> anyhow::Result<()> {
    check_name(name).map_err(|e| anyhow::anyhow!("--name: {e}"))?;
    let mut options = std::fs::OpenOptions::new();
    options.create(true).append(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    let mut f = options
        .open(file)
        .with_context(|| format!("cannot open {}", file.display()))?;
    // A filesystem without locks still gets the entry: the check below then guards alone.
    let _ = f.lock();
    let old =
        std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let mut entry = format!(
        "\n[[tokens]]\nname = {}\nrole = \"{role}\"\nsha256 = \"{}\"\n",
        toml_string(name),
        hash_token(token)?
    );
    if let Some(r) = rate {
        entry.push_str(&format!("rate = {r}\n"));
    }
    let new = format!("{old}{entry}");
    if let Err(e) = Auth::from_toml(&new, RateLimit::default()) {
        if old.is_empty() {
            let _ = std::fs::remove_file(file); // made just now, by this call
        }
        return Err(e)
            .with_context(|| format!("{} would not read after adding {name:?}", file.display()));
    }
    f.write_all(entry.as_bytes())
        .with_context(|| format!("cannot write {}", file.display()))?;
    Ok(())
}

fn toml_string(s: &str) -> String {
    // Names are checked to plain characters; quoting is still done properly.
    format!("\"{}\"", s.replace('\\', "\\\\").replace('"', "\\\""))
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALICE: &str = "alice-token-0123456789abcdef";
    const BOB: &str = "bob-token-0123456789abcdef00";

    fn sample() -> Auth {
        let text = format!(
            "[[tokens]]\nname = \"alice\"\nrole = \"editor\"\nsha256 = \"{}\"\n\n\
             [[tokens]]\nname = \"bob\"\nrole = \"viewer\"\nsha256 = \"{}\"\nrate = 2\n",
            hash_token(ALICE).unwrap(),
            hash_token(BOB).unwrap()
        );
        Auth::from_toml(&text, RateLimit::default()).unwrap()
    }

    /// A shared tokens file read again when it changes: a token added is accepted; a
    /// file that no longer reads keeps the tokens in force (and is read again when it
    /// changes again).
    #[test]
    fn a_changed_tokens_file_is_read_again_and_a_broken_one_keeps_the_old_tokens() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("tokens.toml");
        add_token(&file, "alice", Role::Editor, None, ALICE).unwrap();
        let auth = Auth::from_file(&file, RateLimit::default()).unwrap();
        assert!(auth.reload_if_changed().is_none(), "nothing changed");
        assert_eq!(auth.check(Some(BOB), None).unwrap().role, None);

        add_token(&file, "bob", Role::Viewer, None, BOB).unwrap();
        let summary = auth.reload_if_changed().unwrap().unwrap();
        assert!(summary.starts_with("2 tokens"), "{summary}");
        assert_eq!(
            auth.check(Some(BOB), None).unwrap().role,
            Some(Role::Viewer)
        );

        let text = std::fs::read_to_string(&file).unwrap();
        std::fs::write(&file, format!("{text}\n[[tokens]]\nname = \"half\"\n")).unwrap();
        let e = auth.reload_if_changed().unwrap().unwrap_err();
        assert!(format!("{e:#}").contains("tokens[2]"), "{e:#}");
        assert!(
            !format!("{e:#}").contains(&hash_token(BOB).unwrap()),
            "{e:#}"
        );
        assert_eq!(
            auth.check(Some(BOB), None).unwrap().role,
            Some(Role::Viewer)
        );
        assert!(
            auth.reload_if_changed().is_none(),
            "the error is reported once"
        );
        std::fs::write(&file, text).unwrap();
        std::fs::remove_file(&file).unwrap();
        assert!(auth.reload_if_changed().unwrap().is_err(), "a missing file");
        assert_eq!(
            auth.check(Some(ALICE), None).unwrap().role,
            Some(Role::Editor)
        );
    }

    #[test]
    fn sha256_matches_a_published_vector() {
        // FIPS 180-2 example: SHA-256("abc").
        assert_eq!(
            hex(&sha256(b"abc")),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn roles_and_routes() {
        use Role::*;
        assert!(Viewer < Editor && Editor < Admin);
        let get = Method::GET;
        assert_eq!(required_role(&get, "/"), None);
        assert_eq!(required_role(&get, "/healthz"), None);
        assert_eq!(required_role(&get, "/metrics"), None);
        assert_eq!(required_role(&get, "/viewer.js"), None);
        assert_eq!(required_role(&get, "/apix"), None);
        assert_eq!(required_role(&get, "/api/v1/scenes"), Some(Viewer));
        assert_eq!(required_role(&get, "/api"), Some(Viewer));
        assert_eq!(required_role(&get, "/api/v1/scenes/x/stream"), Some(Viewer));
        assert_eq!(
            required_role(&Method::POST, "/api/v1/scenes/x/relight"),
            Some(Viewer)
        );
        assert_eq!(required_role(&Method::POST, "/api/v1/scenes"), Some(Editor));
        assert_eq!(
            required_role(&Method::POST, "/api/v1/scenes/"),
            Some(Editor)
        );
        assert_eq!(required_role(&get, "/api/v1/jobs/j1/events"), Some(Editor));
        assert_eq!(
            required_role(&Method::DELETE, "/api/v1/jobs/j1"),
            Some(Editor)
        );
        assert_eq!(
            required_role(&Method::DELETE, "/api/v1/scenes/x"),
            Some(Admin)
        );
        assert_eq!(required_role(&get, "/api/v2/anything"), Some(Viewer));
    }

    #[test]
    fn check_decides() {
        let a = sample();
        assert!(a.enabled());
        assert_eq!(a.check(None, Some(Role::Viewer)), Err(Denied::Missing));
        assert_eq!(
            a.check(Some("nope"), Some(Role::Viewer)),
            Err(Denied::Unknown)
        );
        assert_eq!(a.check(Some(""), Some(Role::Viewer)), Err(Denied::Unknown));
        let id = a.check(Some(ALICE), Some(Role::Editor)).unwrap();
        assert_eq!((&*id.name, id.role), ("alice", Some(Role::Editor)));
        assert_eq!(
            a.check(Some(BOB), Some(Role::Editor)),
            Err(Denied::Forbidden {
                has: Role::Viewer,
                needs: Role::Editor
            })
        );
        assert_eq!(
            a.check(Some(ALICE), Some(Role::Admin)),
            Err(Denied::Forbidden {
                has: Role::Editor,
                needs: Role::Admin
            })
        );
        // Open routes: anonymous without a token, named with one.
        assert_eq!(&*a.check(None, None).unwrap().name, ANONYMOUS_NAME);
        assert_eq!(&*a.check(Some(BOB), None).unwrap().name, "bob");
        // No tokens: everything allowed, as the local user.
        let open = Auth::open();
        assert!(!open.enabled());
        assert_eq!(
            &*open.check(None, Some(Role::Admin)).unwrap().name,
            LOCAL_NAME
        );
    }

    #[test]
    fn token_bucket() {
        let a = sample();
        let bob: Arc<str> = "bob".into();
        // Bob: 2 per second, burst max(100, 2) = 100 at the start.
        let mut ok = 0;
        while a.take(&bob).is_ok() {
            ok += 1;
            assert!(ok <= 100, "the bucket never empties");
        }
        assert_eq!(ok, 100);
        let wait = a.take(&bob).unwrap_err();
        assert!(wait > 0.0 && wait <= 0.5 + 1e-9, "{wait}");
        // Alice has her own bucket.
        assert!(a.take(&"alice".into()).is_ok());
    }

    #[test]
    fn file_errors_name_the_entry() {
        let h = hash_token(ALICE).unwrap();
        let cases = [
            (
                format!("[[tokens]]\nname = \"a\"\nrole = \"viewer\"\ntoken = \"{ALICE}\"\n"),
                "plain-text",
            ),
            (
                "[[tokens]]\nname = \"a\"\nrole = \"boss\"\nsha256 = \"00\"\n".to_string(),
                "tokens[0]",
            ),
            (
                "[[tokens]]\nname = \"a\"\nrole = \"viewer\"\nsha256 = \"00\"\n".to_string(),
                "tokens[0].sha256",
            ),
            (
                format!("[[tokens]]\nname = \"a b\"\nrole = \"viewer\"\nsha256 = \"{h}\"\n"),
                "tokens[0].name",
            ),
            (
                format!(
                    "[[tokens]]\nname = \"a\"\nrole = \"viewer\"\nsha256 = \"{h}\"\n\
                     [[tokens]]\nname = \"b\"\nrole = \"admin\"\nsha256 = \"{h}\"\n"
                ),
                "tokens[1].sha256",
            ),
            (
                format!(
                    "[[tokens]]\nname = \"a\"\nrole = \"viewer\"\nsha256 = \"{h}\"\nrate = -1\n"
                ),
                "tokens[0].rate",
            ),
            (String::new(), "no [[tokens]]"),
            ("tokens = 3".to_string(), "line 1"),
        ];
        for (text, want) in cases {
            let e = format!(
                "{:#}",
                Auth::from_toml(&text, RateLimit::default()).unwrap_err()
            );
            assert!(e.contains(want), "{text:?}: {e}");
            assert!(!e.contains(ALICE), "the error repeats a token: {e}");
        }
        assert!(hash_token("short").is_err());
    }

    #[test]
    fn add_appends_a_readable_entry() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("tokens.toml");
        let t1 = new_token().unwrap();
        let t2 = new_token().unwrap();
        assert_ne!(t1, t2);
        assert_eq!(t1.len(), 4 + 64);
        add_token(&file, "ops", Role::Admin, None, &t1).unwrap();
        add_token(&file, "ci", Role::Viewer, Some(5.0), &t2).unwrap();
        assert!(add_token(&file, "ops", Role::Viewer, None, &new_token().unwrap()).is_err());
        let text = std::fs::read_to_string(&file).unwrap();
        assert!(!text.contains(&t1) && !text.contains(&t2), "{text}");
        let a = Auth::from_file(&file, RateLimit::default()).unwrap();
        assert_eq!(
            a.check(Some(&t1), Some(Role::Admin)).unwrap().name.as_ref(),
            "ops"
        );
        assert_eq!(
            a.check(Some(&t2), Some(Role::Viewer))
                .unwrap()
                .name
                .as_ref(),
            "ci"
        );
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&file).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode, 0o600);
        }
    }

    #[test]
    fn query_tokens_decode() {
        assert_eq!(percent_decode("tlx_ab%2Bc"), "tlx_ab+c");
        assert_eq!(percent_decode("a+b"), "a b");
        assert_eq!(percent_decode("%zz%4"), "%zz%4");
        assert!(check_bind(&"0.0.0.0:8080".parse().unwrap(), &Auth::open()).is_err());
        assert!(check_bind(&"127.0.0.1:8080".parse().unwrap(), &Auth::open()).is_ok());
        assert!(check_bind(&"[::1]:8080".parse().unwrap(), &Auth::open()).is_ok());
        assert!(check_bind(&"0.0.0.0:8080".parse().unwrap(), &sample()).is_ok());
    }
}
