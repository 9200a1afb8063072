//! `${VAR}` and `${VAR:-default}` substitution in config values (not in comments).
//!
//! The syntax, checked (AimRT substitutes whatever it finds, and an unset variable
//! becomes empty):
//! - `${NAME}`: the variable's value; unset is an error. `${NAME:-default}`: the default
//!   when unset, itself substituted (`${A:-${B:-c}}`, as in the shell). A name is
//!   letters, digits and `_`, not starting with a digit.
//! - `$${` is a literal `${`.
//! - A `${` with no `}` on its line, a reference that is not a name, and a value with a
//!   line break (it would change the file's structure and every later line number) are
//!   errors.

/// Why a config's text cannot be substituted, and where (1-based, in characters).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct SubstError {
    pub(crate) line: usize,
    pub(crate) column: usize,
    pub(crate) message: String,
}

/// How deep references may nest in defaults (`${A:-${B:-c}}` is 2). The shell sets no
/// limit; one keeps a runaway line from exhausting the stack, and each level's text is
/// read once a level, so a line is read at most this many times.
pub(crate) const MAX_NESTING: usize = 16;

/// Substitutes variables using `lookup`. Text after a YAML comment marker (`#` at the
/// start of a line or after whitespace, outside quotes) is left as it is.
pub(crate) fn substitute(
    text: &str,
    lookup: impl Fn(&str) -> Option<String>,
) -> Result<String, SubstError> {
    let mut out = String::with_capacity(text.len());
    for (idx, line) in text.split_inclusive('\n').enumerate() {
        let code_end = comment_start(line).unwrap_or(line.len());
        expand(line, 0..code_end, &lookup, &mut out).map_err(|(at, message)| SubstError {
            line: idx + 1,
            column: line[..at].chars().count() + 1,
            message,
        })?;
        out.push_str(&line[code_end..]);
    }
    Ok(out)
}

/// Appends `line[range]` to `out` with its references substituted. A default is expanded
/// the same way, only when it is used. `Err` holds the byte offset in `line` of the
/// reference at fault (the column is counted from it once, on error: counting it for
/// every reference made a line of many references quadratic).
fn expand(
    line: &str,
    range: std::ops::Range<usize>,
    lookup: &impl Fn(&str) -> Option<String>,
    out: &mut String,
) -> Result<(), (usize, String)> {
    let (mut pos, end) = (range.start, range.end);
    while let Some(found) = line[pos..end].find("${") {
        let start = pos + found;
        if line[pos..start].ends_with('$') {
            // `$${`: a literal `${`.
            out.push_str(&line[pos..start - 1]);
            out.push_str("${");
            pos = start + 2;
            continue;
        }
        let inner = start + 2;
        let len = closing(&line[inner..end]).map_err(|message| (start, message))?;
        let expr = &line[inner..inner + len];
        let (name, default) = match expr.find(":-") {
            Some(i) => (&expr[..i], Some(inner + i + 2..inner + len)),
            None => (expr, None),
        };
        if !is_name(name) {
            return Err((start, format!(
                "'${{{expr}}}' does not name a variable: a name is letters, digits and '_', not starting with a digit (e.g. ${{AIMRT_PLUGIN_DIR}} or ${{LVL:-Info}})"
            )));
        }
        let value = match (lookup(name), default) {
            (Some(v), _) => v,
            (None, Some(d)) => {
                let mut v = String::new();
                expand(line, d, lookup, &mut v)?;
                v
            }
            (None, None) => {
                return Err((start, format!(
                    "environment variable '{name}' is not set; set it, or write ${{{name}:-default}} to give a default"
                )))
            }
        };
        if value.contains(['\n', '\r']) {
            return Err((start, format!(
                "environment variable '{name}' holds a line break; a substituted value must fit on its line"
            )));
        }
        out.push_str(&line[pos..start]);
        out.push_str(&value);
        pos = inner + len + 1;
    }
    out.push_str(&line[pos..end]);
    Ok(())
}

/// The byte offset in `s` (the text after a `${`) of the `}` that closes it: a `${` in
/// a default opens a reference of its own (`${A:-${B:-c}}`), a `$${` does not. `Err`
/// when there is none, or references nest more than [`MAX_NESTING`] deep.
fn closing(s: &str) -> Result<usize, String> {
    let b = s.as_bytes();
    let (mut depth, mut i) = (1, 0);
    while i < b.len() {
        if b[i..].starts_with(b"$${") {
            i += 3;
        } else if b[i..].starts_with(b"${") {
            depth += 1;
            if depth > MAX_NESTING {
                return Err(format!(
                    "references are nested more than {MAX_NESTING} deep (${{A:-${{B:-...}}}}); nest fewer"
                ));
            }
            i += 2;
        } else {
            if b[i] == b'}' {
                depth -= 1;
                if depth == 0 {
                    return Ok(i);
                }
            }
            i += 1;
        }
    }
    Err("'${' is not closed by '}' on its line; write ${NAME} or ${NAME:-default}, or $${ for a literal '${'".to_owned())
}

fn is_name(name: &str) -> bool {
    let mut chars = name.chars();
    chars
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

fn comment_start(line: &str) -> Option<usize> {
    let (mut single, mut double) = (false, false);
    let mut prev = ' ';
    for (i, c) in line.char_indices() {
        match c {
            '\'' if !double => single = !single,
            '"' if !single && prev != '\\' => double = !double,
            '#' if !single && !double && prev.is_whitespace() => return Some(i),
            _ => {}
        }
        prev = c;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(name: &str) -> Option<String> {
        (name == "HOME_DIR").then(|| "/home/x".to_owned())
    }

    #[test]
    fn substitutes_values_and_defaults() {
        let got = substitute("path: ${HOME_DIR}/lib.so\nlvl: ${LVL:-Info}\n", env).unwrap();
        assert_eq!(got, "path: /home/x/lib.so\nlvl: Info\n");
    }

    #[test]
    fn leaves_comments_alone() {
        let got = substitute("a: 1 # uses ${NOPE}\n# ${NOPE}\nb: '#${HOME_DIR}'\n", env).unwrap();
        assert_eq!(got, "a: 1 # uses ${NOPE}\n# ${NOPE}\nb: '#/home/x'\n");
    }

    #[test]
    fn unset_variable_is_an_error_with_position() {
        let err = substitute("a: 1\nb: x${MISSING}\n", env).unwrap_err();
        assert_eq!((err.line, err.column), (2, 5));
        assert!(
            err.message.contains("'MISSING' is not set"),
            "{}",
            err.message
        );
    }

    #[test]
    fn dollar_dollar_is_a_literal_and_is_not_substituted() {
        let got = substitute("a: $${HOME_DIR} and ${HOME_DIR}\n", env).unwrap();
        assert_eq!(got, "a: ${HOME_DIR} and /home/x\n");
    }

    #[test]
    fn malformed_references_are_errors_with_their_position() {
        let cases = [
            ("lvl: ${LVL:-Info\n", 6, "is not closed"),
            (
                "p: é${ HOME_DIR }\n",
                5,
                "'${ HOME_DIR }' does not name a variable",
            ),
            ("p: ${}\n", 4, "'${}' does not name a variable"),
            ("p: ${1X:-a}\n", 4, "does not name a variable"),
        ];
        for (text, column, says) in cases {
            let err = substitute(text, env).unwrap_err();
            assert_eq!((err.line, err.column), (1, column), "{text}");
            assert!(err.message.contains(says), "{text}: {}", err.message);
        }
    }

    #[test]
    fn a_default_may_hold_references_and_is_read_only_when_used() {
        let got = substitute("a: ${A:-${HOME_DIR:-d}/x}\n", env).unwrap();
        assert_eq!(got, "a: /home/x/x\n");
        let got = substitute("a: ${A:-${B:-${C:-c}}}y}\n", env).unwrap();
        assert_eq!(got, "a: cy}\n");
        let got = substitute("a: ${HOME_DIR:-${UNSET}}\n", env).unwrap();
        assert_eq!(got, "a: /home/x\n");
        let got = substitute("a: ${A:-$${B}}\n", env).unwrap();
        assert_eq!(got, "a: ${B}\n");
        let got = substitute("a: ${A:-{b}}\n", env).unwrap();
        assert_eq!(got, "a: {b}\n");
        let err = substitute("a: ${A:-é${UNSET}}\n", env).unwrap_err();
        assert_eq!((err.line, err.column), (1, 10));
        assert!(
            err.message.contains("'UNSET' is not set"),
            "{}",
            err.message
        );
        let err = substitute("a: ${A:-${B:-c}\n", env).unwrap_err();
        assert_eq!((err.line, err.column), (1, 4));
        assert!(err.message.contains("not closed"), "{}", err.message);
    }

    #[test]
    fn a_value_with_a_line_break_is_refused() {
        let lookup = |_: &str| Some("x\nevil: 1".to_owned());
        let err = substitute("a: ${X}\n", lookup).unwrap_err();
        assert!(err.message.contains("line break"), "{}", err.message);
        let err = substitute("a: ${X:-a\n", env).unwrap_err();
        assert!(err.message.contains("not closed"), "{}", err.message);
    }

    #[test]
    fn references_nested_too_deep_are_an_error_not_a_stack_overflow() {
        let deep = |n: usize| format!("a: {}x{}\n", "${A:-".repeat(n), "}".repeat(n));
        assert_eq!(substitute(&deep(MAX_NESTING), env).unwrap(), "a: x\n");
        let err = substitute(&deep(MAX_NESTING + 1), env).unwrap_err();
        assert_eq!((err.line, err.column), (1, 4));
        assert!(
            err.message.contains("nested more than 16"),
            "{}",
            err.message
        );
        // Far deeper than a thread's stack could recurse: refused, not a crash.
        let err = substitute(&deep(1_000_000), env).unwrap_err();
        assert!(
            err.message.contains("nested more than 16"),
            "{}",
            err.message
        );
    }

    #[test]
    fn a_line_of_many_references_is_read_once() {
        let n = 200_000;
        let got = substitute(&format!("a: é{}\n", "${HOME_DIR}$${".repeat(n)), env).unwrap();
        assert_eq!(got, format!("a: é{}\n", "/home/x${".repeat(n)));
        let err =
            substitute(&format!("a: {}${{NOPE}}\n", "é${HOME_DIR}".repeat(n)), env).unwrap_err();
        assert_eq!((err.line, err.column), (1, 4 + 12 * n));
    }
}
