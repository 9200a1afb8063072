//! AimRT's parameter subsystem: each module's (and plugin's) own store of text values by
//! text key. No options; nothing is shared between stores.

use std::collections::BTreeMap;
use std::sync::Mutex;

/// One store.
#[derive(Debug, Default)]
pub(crate) struct Parameters(Mutex<BTreeMap<String, String>>);

impl Parameters {
    fn map(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, String>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn get(&self, key: &str) -> Option<String> {
        self.map().get(key).cloned()
    }

    pub(crate) fn set(&self, key: &str, value: &str) {
        self.map().insert(key.to_owned(), value.to_owned());
    }

    pub(crate) fn remove(&self, key: &str) -> bool {
        self.map().remove(key).is_some()
    }

    pub(crate) fn keys(&self) -> Vec<String> {
        self.map().keys().cloned().collect()
    }
}

/// The `CoreHost` parameter methods of a host object, served by its [`Parameters`] field
/// `$field` (module and plugin cores alike).
macro_rules! serve_parameters {
    ($field:ident) => {
        fn parameter_get(&self, key: &str) -> Option<String> {
            self.$field.get(key)
        }
        fn parameter_set(&self, key: &str, value: &str) {
            self.$field.set(key, value)
        }
        fn parameter_remove(&self, key: &str) -> bool {
            self.$field.remove(key)
        }
        fn parameter_keys(&self) -> Vec<String> {
            self.$field.keys()
        }
    };
}
pub(crate) use serve_parameters;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_get_remove_and_keys_in_byte_order() {
        let p = Parameters::default();
        assert_eq!(p.get("a"), None);
        p.set("b", "2");
        p.set("a", "1");
        p.set("a", "one");
        p.set("empty", "");
        assert_eq!(p.get("a").as_deref(), Some("one"));
        assert_eq!(p.get("empty").as_deref(), Some(""));
        assert_eq!(p.keys(), ["a", "b", "empty"]);
        assert!(p.remove("b"));
        assert!(!p.remove("b"));
        assert_eq!(p.keys(), ["a", "empty"]);
    }
}
