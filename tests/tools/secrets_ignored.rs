//! Secrets stay out of the repository (issue 56): git ignores a `tokens` file wherever an example
//! might leave one, and the Python README's auth example writes its tokens outside the checkout.

use std::path::Path;
use std::process::Command;

#[test]
fn git_ignores_token_files_and_the_readme_writes_them_elsewhere() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("clients/python/README.md")).unwrap();
    let auth = readme
        .split("--tokens-file")
        .next()
        .and_then(|before| before.rsplit("```sh").next())
        .expect("the auth example");
    assert!(
        auth.contains("mktemp -d") && !auth.contains("> tokens"),
        "the auth example writes its tokens into the working directory:\n{auth}"
    );
    let git = Command::new("git")
        .arg("-C")
        .arg(root)
        .args([
            "check-ignore",
            "--no-index",
            "tokens",
            "clients/python/tokens",
            "x.tokens",
        ])
        .output();
    match git {
        Ok(out) if out.status.code() != Some(128) => {
            let ignored = String::from_utf8_lossy(&out.stdout);
            assert_eq!(
                ignored.lines().count(),
                3,
                "git does not ignore every token file: {ignored}"
            );
        }
        // No git, or not a checkout (a source tarball): the patterns are read directly.
        _ => {
            let patterns = std::fs::read_to_string(root.join(".gitignore")).unwrap();
            assert!(patterns.lines().any(|l| l.trim() == "tokens"), "{patterns}");
        }
    }
}
