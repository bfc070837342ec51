//! `translux-server --bundles DIR [--addr HOST:PORT]` or `translux-server --demo`; see the
//! library's documentation.

fn main() -> std::process::ExitCode {
    translux_server::cli::main()
}
