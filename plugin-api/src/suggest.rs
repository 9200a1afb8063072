//! "Did you mean …?" for names the user got almost right.

/// The closest candidate to `word` (Levenshtein distance < 4 and less than its length).
pub fn closest<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    candidates
        .into_iter()
        .map(|c| (strsim::levenshtein(word, c), c))
        .filter(|(d, c)| *d < 4 && *d < word.len().max(c.len()))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

/// `; did you mean 'x'?` or nothing.
pub fn did_you_mean<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> String {
    closest(word, candidates).map_or_else(String::new, |c| format!("; did you mean '{c}'?"))
}

/// Rewrites serde's "unknown field `x`, expected one of `a`, `b`" as "unknown key 'x'; did
/// you mean 'a'?" (or the list when nothing is close); other messages pass unchanged.
pub fn explain(message: &str) -> String {
    for (ty, range) in [
        ("u8", "0 ..= 255"),
        ("u16", "0 ..= 65535"),
        ("u32", "0 ..= 4294967295"),
        ("u64", "0 ..= 18446744073709551615"),
        ("i32", "-2147483648 ..= 2147483647"),
        ("i64", "-9223372036854775808 ..= 9223372036854775807"),
    ] {
        if message.trim() == format!("invalid {ty}") {
            return format!("invalid value: expected a whole number in {range}");
        }
    }
    if message.contains("expected mapping start") {
        return "expected a map (key: value) here".to_owned();
    }
    if message.contains("expected sequence start") {
        return "expected a list ([a, b] or lines starting with '- ') here".to_owned();
    }
    if let Some(rest) = message.strip_prefix("duplicate mapping key: ") {
        let key = rest
            .split(", set DuplicateKeyPolicy")
            .next()
            .unwrap_or(rest);
        return format!("duplicate key '{key}'; each key may appear once in a map");
    }
    if let Some(rest) = message.strip_prefix("unknown field `") {
        if let Some((field, expected)) = rest.split_once('`') {
            // serde writes "expected `a`", "expected `a` or `b`" or "expected one of `a`,
            // `b`, `c`" (some deserializers without the backquotes).
            let candidates: Vec<&str> = expected
                .trim_start_matches(", expected one of ")
                .trim_start_matches(", expected ")
                .split(", ")
                .flat_map(|s| s.split(" or "))
                .map(|s| s.trim_matches('`'))
                .filter(|s| !s.is_empty())
                .collect();
            let hint = did_you_mean(field, candidates.iter().copied());
            if !hint.is_empty() {
                return format!("unknown key '{field}'{hint}");
            }
            return format!(
                "unknown key '{field}'; expected one of {}",
                candidates.join(", ")
            );
        }
    }
    message.to_owned()
}

/// Reads an options or config tree given as JSON text into `T`: absent (`null` or empty)
/// reads as `{}`; a node that is not a map, a wrong type or an unknown key is an
/// [`Error::Options`](crate::Error::Options) naming `what` and, for a typo, the closest key.
pub fn read_options<T: serde::de::DeserializeOwned>(
    json: &str,
    what: impl FnOnce() -> String,
) -> Result<T, crate::Error> {
    let text = json.trim();
    let parsed = if text.is_empty() || text == "null" {
        Ok(serde_json::Value::Object(Default::default()))
    } else {
        serde_json::from_str(text).map_err(|e| e.to_string())
    };
    let result = parsed.and_then(|value| {
        if !value.is_object() {
            return Err(format!("expected a map, found {value}"));
        }
        serde_path_to_error::deserialize(value).map_err(|e| {
            let path = e.path().to_string();
            let message = explain(&e.into_inner().to_string());
            if path == "." || message.starts_with("unknown key") {
                message
            } else {
                format!("key '{path}': {message}")
            }
        })
    });
    result.map_err(|message| crate::Error::Options {
        what: what(),
        message,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn suggests_close_names_only() {
        assert_eq!(
            closest("simple_thred", ["simple_thread", "asio_thread"]),
            Some("simple_thread")
        );
        assert_eq!(closest("zzz", ["simple_thread"]), None);
        assert_eq!(
            did_you_mean("optons", ["options", "name"]),
            "; did you mean 'options'?"
        );
    }

    #[test]
    fn unknown_keys_get_a_suggestion_whatever_the_number_of_fields() {
        for (message, expected) in [
            ("unknown field `nam`, expected `name`", "unknown key 'nam'; did you mean 'name'?"),
            (
                "unknown field `subscriber_use_inline_executr`, expected `subscriber_use_inline_executor` or `subscriber_executor`",
                "unknown key 'subscriber_use_inline_executr'; did you mean 'subscriber_use_inline_executor'?",
            ),
            (
                "unknown field `thread_nm`, expected one of `thread_num`, `queue_threshold`, `thread_bind_cpu`",
                "unknown key 'thread_nm'; did you mean 'thread_num'?",
            ),
            (
                "unknown field `zzz`, expected `a` or `b`",
                "unknown key 'zzz'; expected one of a, b",
            ),
        ] {
            assert_eq!(explain(message), expected);
        }
    }
}
