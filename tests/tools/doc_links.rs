//! The library's documentation has no broken links (issue 53, item 4): `cargo doc` with
//! `-D rustdoc::broken_intra_doc_links` (and private items, where most of the design is
//! written). A renamed or moved item whose doc links were left behind fails here, not in a
//! reader's browser. The docs build in their own target directory beside the tests' build, so
//! the running `cargo test` and this `cargo doc` never wait on each other's lock.

use crate::common;

use std::path::PathBuf;
use std::process::Command;

/// `<target>/doc-check`, from this test binary's path (`<target>/<profile>/deps/<binary>`).
fn doc_target_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("the test binary's path");
    let target = exe
        .ancestors()
        .nth(3)
        .expect("the binary sits in <target>/<profile>/deps");
    target.join("doc-check")
}

#[test]
fn the_library_docs_have_no_broken_intra_doc_links() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args([
            "doc",
            "--locked",
            "--lib",
            "--no-deps",
            "--document-private-items",
        ])
        .env("CARGO_TARGET_DIR", doc_target_dir())
        .env("RUSTDOCFLAGS", "-D rustdoc::broken_intra_doc_links")
        .output()
        .expect("cargo runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "cargo doc found broken links:\n{stderr}"
    );
}

/// Every relative link and `#anchor` in the Markdown (README, the guide, BENCHMARKS, the
/// history, the catalogues) resolves: `scripts/check_links.py`, which a writer runs too.
#[test]
fn the_markdown_links_and_anchors_resolve() {
    let root = env!("CARGO_MANIFEST_DIR");
    let out = match Command::new("python3")
        .current_dir(root)
        .arg("scripts/check_links.py")
        .output()
    {
        Ok(out) => out,
        Err(e) => {
            common::skip_or_fail::<()>(&format!("python3 cannot run: {e}"));
            return;
        }
    };
    assert!(
        out.status.success(),
        "broken Markdown links:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
