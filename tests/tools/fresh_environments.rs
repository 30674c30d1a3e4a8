//! The fresh path of the test command's shared environments (issue 52, item 13): on a new
//! machine several tests create the same venv at once. Here four threads make one venv from
//! nothing (an empty cache directory, pip without its download cache) at the same time; each
//! gets a python that has pip and the package. CI machines already
//! hold the real venvs, so this runs on every run to keep the path they skip proven.

use crate::common;

use std::process::Command;
use std::sync::{Arc, Barrier};

use common::environments::{python_venv_in, Pip};

#[test]
fn four_tests_making_one_venv_from_nothing_at_once_all_get_a_working_one() {
    let cache = common::temp_dir("fresh-environments");
    let start = Arc::new(Barrier::new(4));
    let makers: Vec<_> = (0..4)
        .map(|_| {
            let (cache, start) = (cache.clone(), Arc::clone(&start));
            std::thread::spawn(move || {
                start.wait();
                python_venv_in(&cache, "fresh", &[vec!["xxhash".into()]], Pip::NoCache)
            })
        })
        .collect();
    for maker in makers {
        let python = match maker.join().expect("the thread ends") {
            Ok(python) => python,
            Err(reason) => {
                // No Python or no PyPI here: skipped, except under CI.
                common::skip_or_fail::<()>(&format!("cannot make a venv: {reason}"));
                return;
            }
        };
        let out = Command::new(&python)
            .args([
                "-c",
                "import pip, xxhash; print(xxhash.xxh64(b'factord').hexdigest())",
            ])
            .output()
            .expect("python runs");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    assert!(cache.join("venvs/fresh/.factord-venv-made").exists());
    let _ = std::fs::remove_dir_all(&cache);
}
