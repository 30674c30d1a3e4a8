//! Command-line arguments of the bench binaries (`cargo bench --bench <name> -- <args>`),
//! shared by including this file (`#[path = "../args.rs"] mod args;`).
#![allow(dead_code)]

pub struct Args(Vec<String>);

impl Args {
    /// The process's arguments, without the `--bench` that cargo adds.
    pub fn from_env() -> Self {
        Self(
            std::env::args()
                .skip(1)
                .filter(|a| a != "--bench")
                .collect(),
        )
    }

    /// The first argument (a dataset file); panics with `usage` when there is none.
    pub fn first(&self, usage: &str) -> String {
        self.0.first().cloned().unwrap_or_else(|| panic!("{usage}"))
    }

    /// Whether the switch `name` is given.
    pub fn has(&self, name: &str) -> bool {
        self.0.iter().any(|a| a == name)
    }

    /// The value after `name` (`--rounds 5`).
    pub fn value(&self, name: &str) -> Option<String> {
        let at = self.0.iter().position(|a| a == name)?;
        self.0.get(at + 1).cloned()
    }

    /// The value after `name`, parsed; `default` when `name` is absent.
    pub fn parsed<T: std::str::FromStr>(&self, name: &str, default: T) -> T {
        self.value(name).map_or(default, |v| {
            v.parse()
                .unwrap_or_else(|_| panic!("{name}: cannot read `{v}`"))
        })
    }
}
