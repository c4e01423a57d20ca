//! What a head model file does not say: names of its blendshapes and named vertex sets
//! (parts such as eyes, teeth and tongue; regions such as lips). A JSON side file
//! (`head.json` next to `head.npz`); FLAME users may write one by hand or go without.
//!
//! ```json
//! { "shape_names": ["age", ...], "expr_names": ["browDownLeft", ...],
//!   "vertex_sets": { "eye_l": [[start, end], ...], "lips": [[start, end], ...] } }
//! ```
//! Vertex sets are lists of half-open index ranges.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Names and vertex sets of a head model.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HeadMeta {
    /// One name per shape coefficient (may be empty).
    #[serde(default)]
    pub shape_names: Vec<String>,
    /// One name per expression coefficient (may be empty).
    #[serde(default)]
    pub expr_names: Vec<String>,
    /// Named vertex sets as half-open ranges `[start, end)`.
    #[serde(default)]
    pub vertex_sets: BTreeMap<String, Vec<[u32; 2]>>,
}

impl HeadMeta {
    /// Reads `path`.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&text, path)
    }

    /// Parses JSON text; `path` names it in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        serde_json::from_str(text).map_err(|e| {
            Error::invalid(
                path.display().to_string(),
                format!("line {} column {}", e.line(), e.column()),
                e.to_string(),
            )
        })
    }

    /// Writes `path` (pretty JSON).
    pub fn save(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::invalid(path.display().to_string(), "json", e.to_string()))?;
        std::fs::write(path, text).map_err(|e| Error::io(path, e))
    }

    /// Checks the names and sets against a model with `v` vertices, `s` shape and `e`
    /// expression coefficients.
    pub fn validate(&self, what: &str, v: usize, s: usize, e: usize) -> Result<()> {
        if !self.shape_names.is_empty() && self.shape_names.len() != s {
            return Err(Error::invalid(
                what,
                "shape_names",
                format!(
                    "{} names for {s} shape coefficients",
                    self.shape_names.len()
                ),
            ));
        }
        if !self.expr_names.is_empty() && self.expr_names.len() != e {
            return Err(Error::invalid(
                what,
                "expr_names",
                format!(
                    "{} names for {e} expression coefficients",
                    self.expr_names.len()
                ),
            ));
        }
        for (name, ranges) in &self.vertex_sets {
            if let Some(r) = ranges.iter().find(|r| r[0] > r[1] || r[1] as usize > v) {
                return Err(Error::invalid(
                    what,
                    format!("vertex_sets.{name}"),
                    format!("range {r:?} is not within 0..{v}"),
                ));
            }
        }
        Ok(())
    }

    /// The index of the expression called `name`.
    pub fn expr(&self, name: &str) -> Option<usize> {
        self.expr_names.iter().position(|n| n == name)
    }

    /// A per-vertex membership mask of set `name` (all false when absent).
    pub fn mask(&self, name: &str, v: usize) -> Vec<bool> {
        let mut m = vec![false; v];
        for r in self.vertex_sets.get(name).into_iter().flatten() {
            let end = (r[1] as usize).min(v);
            if let Some(s) = m.get_mut(r[0] as usize..end) {
                s.fill(true);
            }
        }
        m
    }

    /// Stores a set given as a sorted or unsorted list of vertex indices.
    pub fn set_from_indices(&mut self, name: &str, indices: &[u32]) {
        let mut idx = indices.to_vec();
        idx.sort_unstable();
        idx.dedup();
        let mut ranges: Vec<[u32; 2]> = Vec::new();
        for i in idx {
            match ranges.last_mut() {
                Some(r) if r[1] == i => r[1] = i + 1,
                _ => ranges.push([i, i + 1]),
            }
        }
        self.vertex_sets.insert(name.to_string(), ranges);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sets_round_trip_through_ranges() {
        let mut m = HeadMeta::default();
        m.set_from_indices("a", &[5, 1, 2, 3, 9, 2]);
        assert_eq!(m.vertex_sets["a"], vec![[1, 4], [5, 6], [9, 10]]);
        let mask = m.mask("a", 11);
        let got: Vec<usize> = (0..11).filter(|&i| mask[i]).collect();
        assert_eq!(got, vec![1, 2, 3, 5, 9]);
        assert!(m.validate("m", 10, 0, 0).is_ok());
        let err = m.validate("m", 9, 0, 0).unwrap_err().to_string();
        assert!(err.contains("vertex_sets.a"), "{err}");
        let text = serde_json::to_string(&m).expect("json");
        assert_eq!(
            HeadMeta::parse(&text, Path::new("x.json")).expect("parse"),
            m
        );
        let err = HeadMeta::parse("{\"expr_names\": 3}", Path::new("x.json"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("x.json") && err.contains("line 1"), "{err}");
    }
}
