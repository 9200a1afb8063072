//! "Did you mean …?" for names the user got almost right.

/// The closest candidate to `word` (Levenshtein distance < 4 and less than its length).
pub(crate) fn closest<'a>(
    word: &str,
    candidates: impl IntoIterator<Item = &'a str>,
) -> Option<&'a str> {
    candidates
        .into_iter()
        .map(|c| (strsim::levenshtein(word, c), c))
        .filter(|(d, c)| *d < 4 && *d < word.len().max(c.len()))
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

/// `; did you mean 'x'?` or nothing.
pub(crate) fn did_you_mean<'a>(
    word: &str,
    candidates: impl IntoIterator<Item = &'a str>,
) -> String {
    closest(word, candidates).map_or_else(String::new, |c| format!("; did you mean '{c}'?"))
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
}
