#!/bin/sh
# Stub sources for the Dockerfile's dependency layer: run in a directory holding only Cargo.toml
# and Cargo.lock, it writes an empty library, a `main` that exits with 99, and an empty `main`
# at every target path the manifest names (`path = "..."` lines of [[bench]] and the like), so
# that `cargo build --release --locked` compiles every dependency without our sources. The real
# build replaces them; if a stub binary were ever kept by mistake, `factord --version` at the end
# of the build fails on its 99. tests/tools/docker.rs runs this script and checks that cargo finds
# every target it names.
set -eu
mkdir -p src
: > src/lib.rs
echo 'fn main() { std::process::exit(99) }' > src/main.rs
sed -n 's/^path *= *"\(.*\)" *$/\1/p' Cargo.toml | while read -r target; do
    mkdir -p "$(dirname "$target")"
    echo 'fn main() {}' > "$target"
done
