//! `${VAR}` and `${VAR:-default}` substitution in config values (not in comments).

/// An unset variable without a default.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct UnsetVar {
    pub(crate) name: String,
    pub(crate) line: usize,
    pub(crate) column: usize,
}

/// Substitutes variables using `lookup`. Text after a YAML comment marker (`#` at the
/// start of a line or after whitespace, outside quotes) is left as it is.
pub(crate) fn substitute(
    text: &str,
    lookup: impl Fn(&str) -> Option<String>,
) -> Result<String, UnsetVar> {
    let mut out = String::with_capacity(text.len());
    for (idx, line) in text.split_inclusive('\n').enumerate() {
        let code_end = comment_start(line).unwrap_or(line.len());
        let (code, comment) = line.split_at(code_end);
        let mut rest = code;
        let mut col = 0;
        while let Some(start) = rest.find("${") {
            let Some(len) = rest[start + 2..].find('}') else {
                break;
            };
            let expr = &rest[start + 2..start + 2 + len];
            let (name, default) = match expr.split_once(":-") {
                Some((n, d)) => (n, Some(d)),
                None => (expr, None),
            };
            let value = match (lookup(name), default) {
                (Some(v), _) => v,
                (None, Some(d)) => d.to_owned(),
                (None, None) => {
                    return Err(UnsetVar {
                        name: name.to_owned(),
                        line: idx + 1,
                        column: col + start + 1,
                    })
                }
            };
            out.push_str(&rest[..start]);
            out.push_str(&value);
            col += start + 3 + len;
            rest = &rest[start + 3 + len..];
        }
        out.push_str(rest);
        out.push_str(comment);
    }
    Ok(out)
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
        assert_eq!(
            err,
            UnsetVar {
                name: "MISSING".into(),
                line: 2,
                column: 5
            }
        );
    }
}
