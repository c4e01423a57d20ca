//! Running the built `texavatars` binary from an integration test.

use std::ffi::OsStr;

/// Runs `texavatars ARGS...` and returns its stdout; fails the test with its stderr when it
/// exits non-zero.
pub fn texavatars_ok<I, S>(args: I) -> String
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_texavatars"))
        .args(args)
        .output()
        .expect("run texavatars");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}
