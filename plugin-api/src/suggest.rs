//! "Did you mean …?" for names the user got almost right.

/// The closest candidate to `word` (Levenshtein distance < 4 and less than its length).
///
/// Also used on what peers send (an unknown function or uri), so its cost is bounded:
/// only candidates whose length is within 3 of the word's are compared (a distance under
/// 4 needs that), and a word or candidate over 256 bytes is not compared at all.
pub fn closest<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    const LONGEST: usize = 256;
    if word.len() > LONGEST {
        return None;
    }
    let chars = word.chars().count();
    candidates
        .into_iter()
        .filter(|c| c.len() <= LONGEST && c.chars().count().abs_diff(chars) < 4)
        .map(|c| (strsim::levenshtein(word, c), c))
        .filter(|(d, c)| *d < 4 && *d < word.len().max(c.len()))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

#[cfg(test)]
mod closest_tests {
    use super::{closest, no_such};

    #[test]
    fn only_near_lengths_are_compared_and_long_words_not_at_all() {
        assert_eq!(closest("locl", ["local", "zenoh"]), Some("local"));
        assert_eq!(closest("grüße", ["grüssen"]), Some("grüssen"));
        // A distance under 4 needs lengths within 3 of each other.
        assert_eq!(closest("ab", ["abcdefg"]), None);
        let long = "x".repeat(300);
        assert_eq!(closest(&long, [long.as_str()]), None);
    }

    #[test]
    fn no_such_names_the_unknown_the_closest_and_the_known() {
        assert_eq!(
            no_such("logger", &["Loger", "x"], &["core", "Logger"]),
            "no logger 'Loger', 'x'; did you mean 'Logger'? (the loggers: core, Logger)"
        );
        assert_eq!(
            no_such("module", &["m"], &[]),
            "no module 'm' (the modules: none)"
        );
    }
}

/// `no <what> 'a', 'b'; did you mean 'x'? (the <what>s: x, y)`: names asked for that do not
/// exist (the first 8, then how many more), the closest of the first, and every name that
/// does (`none` when there is none).
pub fn no_such(what: &str, unknown: &[&str], known: &[&str]) -> String {
    const SHOWN: usize = 8;
    let mut asked: Vec<String> = unknown
        .iter()
        .take(SHOWN)
        .map(|n| format!("'{n}'"))
        .collect();
    if unknown.len() > SHOWN {
        asked.push(format!("and {} more", unknown.len() - SHOWN));
    }
    let hint = unknown
        .first()
        .map(|first| did_you_mean(first, known.iter().copied()))
        .unwrap_or_default();
    let list = if known.is_empty() {
        "none".to_owned()
    } else {
        known.join(", ")
    };
    format!("no {what} {}{hint} (the {what}s: {list})", asked.join(", "))
}

/// `; did you mean 'x'?` or nothing.
pub fn did_you_mean<'a>(word: &str, candidates: impl IntoIterator<Item = &'a str>) -> String {
    closest(word, candidates).map_or_else(String::new, |c| format!("; did you mean '{c}'?"))
}

/// The words an error is written in: those of the format the user wrote.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Words {
    /// A config file or options: lists, maps, empty values (`key:` or `~`).
    Yaml,
    /// A JSON body or a JSON5 file: arrays, objects, `null`.
    Json,
}

/// Rewrites serde's messages for a YAML author: "unknown field `x`, expected one of `a`,
/// `b`" as "unknown key 'x'; did you mean 'a'?" (or the list when nothing is close), Rust
/// type names as what to write (`u16` → a whole number of 0 or more, `struct …` → a map
/// (key: value)); other messages pass unchanged.
///
/// ```
/// # use aimrt_plugin_api::__private::explain;
/// assert_eq!(explain("invalid type: integer `5`, expected a sequence"), "expected a list, found integer `5`");
/// ```
pub fn explain(message: &str) -> String {
    explain_in(message, Words::Yaml)
}

/// [`explain`] in the words of JSON, for a JSON body or a JSON5 file: an object where
/// [`explain`] says a map, an array where it says a list, `null` where it says an empty
/// value.
///
/// ```
/// # use aimrt_plugin_api::__private::explain_json;
/// assert_eq!(explain_json("invalid type: sequence, expected a string"), "expected a string, found an array");
/// assert_eq!(
///     explain_json("invalid type: null, expected struct Foo"),
///     "found null where an object is expected; write a value or remove the key"
/// );
/// ```
pub fn explain_json(message: &str) -> String {
    explain_in(message, Words::Json)
}

fn explain_in(message: &str, words: Words) -> String {
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
    if let Some(expected) = message.strip_prefix("invalid type: null, expected ") {
        let found = match words {
            Words::Yaml => "an empty value (null or ~)",
            Words::Json => "null",
        };
        return format!(
            "found {found} where {} is expected; write a value or remove the key",
            in_words(expected, words)
        );
    }
    if let Some((found, expected)) = message
        .strip_prefix("invalid type: ")
        .or_else(|| message.strip_prefix("invalid value: "))
        .and_then(|rest| rest.split_once(", expected "))
    {
        // serde names what it found as `sequence` and `map`, whatever the format.
        let found = match (words, found) {
            (Words::Json, "sequence") => "an array",
            (Words::Json, "map") => "an object",
            _ => found,
        };
        return format!("expected {}, found {found}", in_words(expected, words));
    }
    // serde's derive also reads a struct from a list of its values, in order.
    if let Some((found, fields)) = message
        .strip_prefix("invalid length ")
        .and_then(|rest| rest.split_once(", expected struct "))
        .and_then(|(found, rest)| {
            let fields = rest.strip_suffix(" elements")?.rsplit_once(" with ")?.1;
            Some((found, fields))
        })
    {
        let (map, list) = match words {
            Words::Yaml => (MAP, LIST),
            Words::Json => ("an object", "an array"),
        };
        return format!("expected {map} or {list} of {fields} values, found {list} of {found}");
    }
    if let Some(key) = message
        .strip_prefix("missing field `")
        .and_then(|rest| rest.strip_suffix('`'))
    {
        return format!("the required key '{key}' is missing");
    }
    if let Some(rest) = message.strip_prefix("duplicate mapping key: ") {
        let key = rest
            .split(", set DuplicateKeyPolicy")
            .next()
            .unwrap_or(rest);
        return format!("duplicate key '{key}'; each key may appear once in a map");
    }
    if let Some(key) = message
        .strip_prefix("duplicate field `")
        .and_then(|rest| rest.strip_suffix('`'))
    {
        let map = match words {
            Words::Yaml => "a map",
            Words::Json => "an object",
        };
        return format!("duplicate key '{key}'; each key may appear once in {map}");
    }
    for (prefix, what) in [("unknown field `", "key"), ("unknown variant `", "value")] {
        let Some((word, expected)) = message
            .strip_prefix(prefix)
            .and_then(|rest| rest.split_once('`'))
        else {
            continue;
        };
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
        let hint = did_you_mean(word, candidates.iter().copied());
        if !hint.is_empty() {
            return format!("unknown {what} '{word}'{hint}");
        }
        return format!(
            "unknown {what} '{word}'; expected one of {}",
            candidates.join(", ")
        );
    }
    message.to_owned()
}

/// A list, in [`in_words`] for YAML.
const LIST: &str = "a list";
/// A map, in [`in_words`] for YAML.
const MAP: &str = "a map (key: value)";

/// What serde expects (`a string`, `u32`, `struct Options`, `a sequence`), in the words
/// of the format's author: no Rust type names.
fn in_words(expected: &str, words: Words) -> &str {
    match (words, expected) {
        (Words::Yaml, "a string" | "a character") => "text",
        (Words::Json, "a character") => "a string",
        (_, "a boolean") => "true or false",
        (Words::Yaml, "a sequence") => LIST,
        (Words::Json, "a sequence") => "an array",
        (_, "f32" | "f64") => "a number",
        (_, "u8" | "u16" | "u32" | "u64" | "usize") => "a whole number of 0 or more",
        (_, "i8" | "i16" | "i32" | "i64" | "isize") => "a whole number",
        (Words::Yaml, e) if e.starts_with("struct ") || e.starts_with("a map") => MAP,
        (Words::Json, e) if e.starts_with("struct ") || e.starts_with("a map") => "an object",
        (_, e) => e,
    }
}

/// Reads an options or config tree given as JSON text into `T`: absent (`null` or empty)
/// reads as `{}`; a node that is not a map, a wrong type or an unknown key is an
/// [`Error::Options`](crate::Error::Options) naming `what` and, for a typo, the closest key.
///
/// A key written without a value (`key:` or `key: ~`, which reads as null) where a list or
/// a map is expected reads as an empty one, as the runtime's own sections read it and as
/// AimRT's readers do (a list item commented out leaves its key empty). Where a single
/// value is expected it is an error that says so.
///
/// ```
/// use aimrt_plugin_api::__private::read_options;
/// #[derive(serde::Deserialize)]
/// struct Opts {
///     #[serde(default)]
///     topics: Vec<String>,
///     #[serde(default)]
///     port: u16,
/// }
/// let o: Opts = read_options(r#"{"topics": null}"#, || "options".into()).unwrap();
/// assert!(o.topics.is_empty());
/// let e = read_options::<Opts>(r#"{"port": null}"#, || "options".into()).err().unwrap();
/// assert!(e.to_string().contains("key 'port': found an empty value (null or ~)"));
/// ```
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
        read_with_empty_collections(value)
    });
    result.map_err(|message| crate::Error::Options {
        what: what(),
        message,
    })
}

/// Deserializes `value`, reading a null where a list or a map is expected as an empty one:
/// each such error replaces that null and reads again, so this ends after at most as many
/// tries as `value` holds nulls.
fn read_with_empty_collections<T: serde::de::DeserializeOwned>(
    mut value: serde_json::Value,
) -> Result<T, String> {
    loop {
        let e = match serde_path_to_error::deserialize(&value) {
            Ok(read) => return Ok(read),
            Err(e) => e,
        };
        let message = e.inner().to_string();
        // What serde expected, in the same words the error would use.
        let empty = match message
            .strip_prefix("invalid type: null, expected ")
            .map(|expected| in_words(expected, Words::Yaml))
        {
            Some(LIST) => Some(serde_json::Value::Array(Vec::new())),
            Some(MAP) => Some(serde_json::Value::Object(Default::default())),
            _ => None,
        };
        if empty
            .and_then(|empty| replace_null(&mut value, e.path(), empty))
            .is_some()
        {
            continue;
        }
        let path = e.path().to_string();
        let message = explain(&message);
        return Err(if path == "." || message.starts_with("unknown key") {
            message
        } else {
            format!("key '{path}': {message}")
        });
    }
}

/// Puts `with` where `path` leads in `root` if that is a key whose value is null; `None`
/// otherwise (an empty list item is not a key without a value).
fn replace_null(
    root: &mut serde_json::Value,
    path: &serde_path_to_error::Path,
    with: serde_json::Value,
) -> Option<()> {
    use serde_path_to_error::Segment;
    if !matches!(path.iter().next_back(), Some(Segment::Map { .. })) {
        return None;
    }
    let mut node = root;
    for segment in path {
        node = match segment {
            Segment::Map { key } => node.get_mut(key.as_str())?,
            Segment::Seq { index } => node.get_mut(*index)?,
            Segment::Enum { .. } | Segment::Unknown => return None,
        };
    }
    node.is_null().then(|| *node = with)
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
            ("missing field `path`", "the required key 'path' is missing"),
            (
                "unknown variant `abrt`, expected `log` or `abort`",
                "unknown value 'abrt'; did you mean 'abort'?",
            ),
            (
                "unknown variant `x`, expected `log` or `abort`",
                "unknown value 'x'; expected one of log, abort",
            ),
        ] {
            assert_eq!(explain(message), expected);
        }
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Inner {
        #[serde(default)]
        names: Vec<String>,
        #[serde(default)]
        port: u16,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Outer {
        #[serde(default)]
        list: Vec<Inner>,
        #[serde(default)]
        inner: Option<Inner>,
        #[serde(default)]
        policy: Policy,
        #[serde(default)]
        map: std::collections::BTreeMap<String, u32>,
        #[serde(default)]
        text: String,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Policy {
        size: u32,
    }

    impl Default for Policy {
        fn default() -> Self {
            Policy { size: 7 }
        }
    }

    fn read(json: &str) -> Result<Outer, String> {
        read_options(json, || "options".to_owned()).map_err(|e| e.to_string())
    }

    #[test]
    fn a_key_without_a_value_where_a_list_or_a_map_is_expected_reads_as_empty() {
        let o = read(r#"{"list": null, "policy": null, "map": null, "inner": null}"#).unwrap();
        assert!(o.list.is_empty() && o.map.is_empty() && o.inner.is_none() && o.text.is_empty());
        assert_eq!(o.policy.size, 7, "a map read as empty takes its defaults");
        // Nested in a list, and several in one tree.
        let o = read(r#"{"list": [{"names": null}, {"names": ["a"]}, {"names": null}]}"#).unwrap();
        let lens: Vec<usize> = o.list.iter().map(|i| i.names.len()).collect();
        assert_eq!(lens, [0, 1, 0]);
        let o = read(r#"{"inner": {"names": null, "port": 5}}"#).unwrap();
        assert_eq!(o.inner.map(|i| (i.names.len(), i.port)), Some((0, 5)));
    }

    #[test]
    fn a_key_without_a_value_where_a_value_is_expected_says_so_with_its_path() {
        let e = read(r#"{"text": null}"#).unwrap_err();
        assert!(e.ends_with("key 'text': found an empty value (null or ~) where text is expected; write a value or remove the key"), "{e}");
        let e = read(r#"{"list": [{"names": null}, {"port": null}]}"#).unwrap_err();
        assert!(e.contains("key 'list[1].port': found an empty value (null or ~) where a whole number of 0 or more is expected"), "{e}");
        // An empty list item is not a map to fill: it is reported, not read as defaults.
        let e = read(r#"{"list": [null]}"#).unwrap_err();
        assert!(e.contains("key 'list[0]': found an empty value (null or ~) where a map (key: value) is expected"), "{e}");
    }

    #[test]
    fn a_value_of_the_wrong_type_is_named_without_rust_type_names() {
        let e = read(r#"{"policy": 5}"#).unwrap_err();
        assert!(
            e.ends_with("key 'policy': expected a map (key: value), found integer `5`"),
            "{e}"
        );
        let e = read(r#"{"list": "a"}"#).unwrap_err();
        assert!(
            e.ends_with("key 'list': expected a list, found string \"a\""),
            "{e}"
        );
        let e = read(r#"{"map": {"k": -1}}"#).unwrap_err();
        assert!(
            e.ends_with("key 'map.k': expected a whole number of 0 or more, found integer `-1`"),
            "{e}"
        );
    }
}
