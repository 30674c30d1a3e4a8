//! The estimate: variables addressed by 64-bit keys, each fixed or free.

use std::collections::hash_map::Entry;
use std::collections::HashMap;

use super::{Key, Variable};

/// The key → index map's hasher: foldhash, seeded per process (keys arrive from clients, so not
/// an unseeded hash an attacker could collide), several times faster than the standard SipHash
/// on 64-bit keys. Building a problem looks every factor's keys up: on intel (1 228 poses,
/// 1 483 factors) that was most of the 0.37 ms an in-process `solve` spent before solving.
type KeyHasher = foldhash::fast::RandomState;

#[derive(Debug, Default)]
pub struct Values {
    keys: Vec<Key>,
    index: HashMap<Key, usize, KeyHasher>,
    variables: Vec<Box<dyn Variable>>,
    fixed: Vec<bool>,
}

impl Clone for Values {
    fn clone(&self) -> Self {
        Self {
            keys: self.keys.clone(),
            index: self.index.clone(),
            variables: self.variables.iter().map(|v| v.clone_box()).collect(),
            fixed: self.fixed.clone(),
        }
    }
}

impl Values {
    pub fn len(&self) -> usize {
        self.keys.len()
    }
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }
    /// Inserts a new variable; returns its dense index, or `None` if the key already exists.
    pub fn insert(&mut self, key: Key, variable: Box<dyn Variable>) -> Option<usize> {
        let idx = self.keys.len();
        match self.index.entry(key) {
            Entry::Occupied(_) => return None,
            Entry::Vacant(slot) => slot.insert(idx),
        };
        self.keys.push(key);
        self.variables.push(variable);
        self.fixed.push(false);
        Some(idx)
    }
    pub fn index_of(&self, key: Key) -> Option<usize> {
        self.index.get(&key).copied()
    }
    pub fn key(&self, idx: usize) -> Key {
        self.keys[idx]
    }
    pub fn keys(&self) -> &[Key] {
        &self.keys
    }
    pub fn variable(&self, idx: usize) -> &dyn Variable {
        self.variables[idx].as_ref()
    }
    pub fn variable_mut(&mut self, idx: usize) -> &mut dyn Variable {
        self.variables[idx].as_mut()
    }
    pub fn get(&self, key: Key) -> Option<&dyn Variable> {
        self.index_of(key).map(|i| self.variables[i].as_ref())
    }
    /// The variable under `key` as a concrete kind.
    pub fn get_as<T: Variable>(&self, key: Key) -> Option<&T> {
        self.get(key).and_then(|v| v.as_any().downcast_ref::<T>())
    }
    pub fn is_fixed(&self, idx: usize) -> bool {
        self.fixed[idx]
    }
    pub fn set_fixed(&mut self, idx: usize, fixed: bool) {
        self.fixed[idx] = fixed;
    }
    /// Copies every variable of `other` (same keys, same order) into `self` without allocating.
    pub(crate) fn assign_from(&mut self, other: &Values) {
        debug_assert_eq!(self.keys, other.keys);
        for (dst, src) in self.variables.iter_mut().zip(&other.variables) {
            let same_kind = dst.assign_from(src.as_ref());
            debug_assert!(same_kind);
        }
    }
    /// Replaces the variable at `idx` with a value of the same kind.
    pub fn set(&mut self, idx: usize, variable: &dyn Variable) -> bool {
        self.variables[idx].assign_from(variable)
    }
}
