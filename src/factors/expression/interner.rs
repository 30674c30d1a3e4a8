//! Compiled factor types shared across the server: sessions that declare the same definition
//! (byte for byte, name included) hold one compiled type, compiled once.
//!
//! Entries are keyed by a hash of the definition's JSON encoding and compared in full, and hold
//! the compiled type weakly: it lives as long as a session (or a factor) holds it. A definition
//! being compiled is compiled by one caller; the others asking for it meanwhile wait for that
//! result instead of compiling their own copy (N sessions recovering with the same types compile
//! them once). A refused definition is not remembered: asking again compiles it again.
//!
//! The server's total (every live compiled type, once) is bounded: a definition that must be
//! compiled is refused when the total would pass the bound. Sharing a type already held costs
//! nothing more, so it is never refused by that bound.

use std::collections::hash_map::DefaultHasher;
use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};

use super::{DefinitionError, ExpressionType, FactorTypeDefinition};

#[derive(Default)]
pub struct TypeInterner {
    entries: Mutex<HashMap<u64, Vec<Arc<Entry>>>>,
    compiles: AtomicU64,
    reuses: AtomicU64,
}

struct Entry {
    /// The definition's JSON encoding: what a request must match to share the type.
    canonical: Vec<u8>,
    /// Held while the type is compiled, so one caller compiles it and the others wait.
    compiling: Mutex<()>,
    /// The compiled type, when one is alive, and its bytes (read without upgrading).
    compiled: Mutex<(Weak<ExpressionType>, usize)>,
}

impl Entry {
    fn live(&self) -> Option<(Arc<ExpressionType>, usize)> {
        let compiled = self.compiled.lock().unwrap_or_else(PoisonError::into_inner);
        compiled.0.upgrade().map(|ty| (ty, compiled.1))
    }

    fn live_bytes(&self) -> Option<usize> {
        let compiled = self.compiled.lock().unwrap_or_else(PoisonError::into_inner);
        (compiled.0.strong_count() > 0).then_some(compiled.1)
    }
}

/// Why a definition got no compiled type.
#[derive(Debug, thiserror::Error)]
pub enum InternError {
    #[error(transparent)]
    Definition(#[from] DefinitionError),
    #[error(
        "compiling it needs {needed} bytes and the server's factor types hold {held} of their \
         {bound} (limits.max_factor_type_bytes)"
    )]
    ServerFull {
        needed: usize,
        held: usize,
        bound: usize,
    },
}

/// The compiled types alive in the server, each counted once.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TypesHeld {
    pub types: usize,
    pub bytes: usize,
}

impl std::fmt::Debug for TypeInterner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TypeInterner")
            .field("compiles", &self.compiles())
            .field("reuses", &self.reuses())
            .finish_non_exhaustive()
    }
}

impl TypeInterner {
    /// The compiled type of `definition`: one held already, else compiled now (refused when it
    /// would take the server's total past `bound`; `None` for recovery, which rebuilds what was
    /// accepted once).
    pub fn compile(
        &self,
        definition: FactorTypeDefinition,
        bound: Option<usize>,
    ) -> Result<Arc<ExpressionType>, InternError> {
        let canonical = serde_json::to_vec(&definition).expect("a definition encodes as JSON");
        let entry = self.entry(canonical);
        let _compiling = entry
            .compiling
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if let Some((ty, _)) = entry.live() {
            self.reuses.fetch_add(1, Ordering::Relaxed);
            return Ok(ty);
        }
        let held = self.held().bytes;
        if let Some(bound) = bound.filter(|&b| held >= b) {
            return Err(InternError::ServerFull {
                needed: 0,
                held,
                bound,
            });
        }
        let ty = ExpressionType::compile(definition)?;
        self.compiles.fetch_add(1, Ordering::Relaxed);
        let needed = ty.memory_bytes();
        if let Some(bound) = bound.filter(|&b| held + needed > b) {
            return Err(InternError::ServerFull {
                needed,
                held,
                bound,
            });
        }
        *entry
            .compiled
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = (Arc::downgrade(&ty), needed);
        Ok(ty)
    }

    /// The entry for `canonical`, made when there is none; drops the dead entries of its bucket.
    fn entry(&self, canonical: Vec<u8>) -> Arc<Entry> {
        let mut hasher = DefaultHasher::new();
        canonical.hash(&mut hasher);
        let mut entries = self.entries.lock().unwrap_or_else(PoisonError::into_inner);
        let bucket = entries.entry(hasher.finish()).or_default();
        // An entry nobody else holds is not being compiled: it is dead unless its type lives.
        bucket.retain(|e| Arc::strong_count(e) > 1 || e.live_bytes().is_some());
        if let Some(entry) = bucket.iter().find(|e| e.canonical == canonical) {
            return Arc::clone(entry);
        }
        let entry = Arc::new(Entry {
            canonical,
            compiling: Mutex::new(()),
            compiled: Mutex::new((Weak::new(), 0)),
        });
        bucket.push(Arc::clone(&entry));
        entry
    }

    /// The live compiled types and their bytes (each once, with the definitions kept to match
    /// them); forgets the dead ones.
    pub fn held(&self) -> TypesHeld {
        let mut entries = self.entries.lock().unwrap_or_else(PoisonError::into_inner);
        let mut held = TypesHeld::default();
        entries.retain(|_, bucket| {
            bucket.retain(|e| match e.live_bytes() {
                Some(bytes) => {
                    held.types += 1;
                    held.bytes += bytes + e.canonical.capacity();
                    true
                }
                None => Arc::strong_count(e) > 1,
            });
            !bucket.is_empty()
        });
        held
    }

    /// Definitions compiled so far, and requests served with a type already compiled.
    pub fn compiles(&self) -> u64 {
        self.compiles.load(Ordering::Relaxed)
    }
    pub fn reuses(&self) -> u64 {
        self.reuses.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    fn definition(name: &str, scale: f64) -> FactorTypeDefinition {
        serde_json::from_value(json!({
            "name": name,
            "variables": [{"name": "a", "kind": "se2"}],
            "residual": {"mul": [scale, {"translation": ["a"]}]},
        }))
        .unwrap()
    }

    #[test]
    fn identical_definitions_share_one_compiled_type_while_it_lives() {
        let interner = TypeInterner::default();
        let a = interner.compile(definition("t", 2.0), None).unwrap();
        let b = interner.compile(definition("t", 2.0), None).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert_eq!((interner.compiles(), interner.reuses()), (1, 1));
        // Another constant, or another name: another type.
        let c = interner.compile(definition("t", 3.0), None).unwrap();
        let d = interner.compile(definition("u", 2.0), None).unwrap();
        assert!(!Arc::ptr_eq(&a, &c) && !Arc::ptr_eq(&a, &d));
        let held = interner.held();
        assert_eq!(held.types, 3);
        assert!(held.bytes >= a.memory_bytes() + c.memory_bytes() + d.memory_bytes());
        drop((a, b, c, d));
        assert_eq!(interner.held(), TypesHeld::default());
        // Gone: compiled again.
        let _again = interner.compile(definition("t", 2.0), None).unwrap();
        assert_eq!(interner.compiles(), 4);
    }

    #[test]
    fn the_server_bound_refuses_new_types_but_not_shared_ones() {
        let interner = TypeInterner::default();
        let a = interner.compile(definition("t", 2.0), None).unwrap();
        let bound = interner.held().bytes + 1;
        let refused = interner.compile(definition("u", 2.0), Some(bound));
        assert!(
            matches!(refused, Err(InternError::ServerFull { .. })),
            "{refused:?}"
        );
        let shared = interner.compile(definition("t", 2.0), Some(bound)).unwrap();
        assert!(Arc::ptr_eq(&a, &shared));
        // Recovery passes no bound.
        interner.compile(definition("u", 2.0), None).unwrap();
    }

    #[test]
    fn concurrent_requests_for_one_definition_compile_it_once() {
        let interner = Arc::new(TypeInterner::default());
        let threads: Vec<_> = (0..4)
            .map(|_| {
                let interner = Arc::clone(&interner);
                std::thread::spawn(move || interner.compile(definition("t", 2.0), None).unwrap())
            })
            .collect();
        let types: Vec<_> = threads.into_iter().map(|t| t.join().unwrap()).collect();
        assert!(types.windows(2).all(|w| Arc::ptr_eq(&w[0], &w[1])));
        assert_eq!(interner.compiles(), 1);
    }
}
