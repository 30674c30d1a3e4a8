//! `proto/v1/factors.schema.json` is exactly what `api::factor_schema` generates from the factors'
//! declarations: a factor added, renamed or resized in code without regenerating the schema fails
//! here. `FACTORD_BLESS=1 cargo test --test api factor_schema::` rewrites the file.

use std::path::PathBuf;

use factord::api::factor_schema::{factor_schema, factor_schema_text, PATH};
use serde_json::Value;

#[test]
fn committed_factor_schema_is_the_generated_one() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(PATH);
    if std::env::var("FACTORD_BLESS").is_ok_and(|v| v == "1") {
        std::fs::write(&path, factor_schema_text()).expect("schema written");
        eprintln!("rewrote {}", path.display());
    }
    let committed = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{} unreadable ({e}); regenerate it with `FACTORD_BLESS=1 cargo test --test api factor_schema::`", path.display()));
    let committed: Value = serde_json::from_str(&committed).expect("committed schema is JSON");
    assert!(
        committed == factor_schema(),
        "{PATH} differs from what src/api/factor_schema.rs generates from the factors' WIRE \
         declarations; regenerate it with `FACTORD_BLESS=1 cargo test --test api factor_schema::` and \
         commit the result"
    );
}
