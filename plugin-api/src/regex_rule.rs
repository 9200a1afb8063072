//! The regular expressions of AimRT's routing rules (`topic_name`, `func_name`,
//! `module_filter`): matched against the whole name, with errors that point into what
//! the user wrote.

/// `pattern` compiled to match a whole name (`^(?:pattern)$`), as AimRT's `std::regex_match`.
/// `Err` says what is wrong and where, in the user's pattern (not in the anchored one).
///
/// ```
/// use aimrt_plugin_api::whole_match;
/// let re = whole_match("test_.*").unwrap();
/// assert!(re.is_match("test_topic") && !re.is_match("my_test_topic"));
/// assert_eq!(
///     whole_match("(.*").unwrap_err(),
///     "unclosed group, at character 1: '(.*'"
/// );
/// ```
pub fn whole_match(pattern: &str) -> Result<regex::Regex, String> {
    regex::Regex::new(&format!("^(?:{pattern})$")).map_err(|anchored| {
        match regex_syntax::ast::parse::Parser::new().parse(pattern) {
            Err(e) => {
                let at = e.span().start.offset;
                let from: String = pattern[at..].chars().take(24).collect();
                let more = if pattern[at..].chars().count() > 24 {
                    "…"
                } else {
                    ""
                };
                format!(
                    "{}, at character {}: '{from}{more}'",
                    e.kind(),
                    e.span().start.column
                )
            }
            // It parses but does not compile (too large, a class it cannot build): the
            // regex crate's last line says why.
            Ok(_) => anchored
                .to_string()
                .lines()
                .last()
                .unwrap_or("")
                .trim_start_matches("error: ")
                .to_owned(),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_point_into_the_users_pattern() {
        for (pattern, says) in [
            ("(.*", "unclosed group, at character 1: '(.*'"),
            ("a)", "unopened group, at character 2: ')'"),
            ("topic_[a-", "unclosed character class, at character 7: '[a-'"),
            ("x{2,1}", "invalid repetition count range, the start must be <= the end, at character 2: '{2,1}'"),
            ("*abc", "repetition operator missing expression, at character 1: '*abc'"),
        ] {
            let e = whole_match(pattern).unwrap_err();
            assert!(e.starts_with(says), "{pattern}: {e}");
            assert!(!e.contains("(?:"), "{pattern}: {e}");
        }
        let re = whole_match("(.*)").unwrap();
        assert!(re.is_match("") && re.is_match("any/topic"));
        assert!(!whole_match("a|b").unwrap().is_match("ab"));
    }
}
