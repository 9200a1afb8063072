//! The initialization report (`--dump_init_report`), laid out as AimRT's: numbered sections
//! with ASCII tables.

/// Draws `rows` (the first is the header, unless `header` is false) as an ASCII table with
/// cells padded by two spaces, AimRT's `DrawTable`. Multi-line cells are split over lines.
pub(crate) fn table(rows: &[Vec<String>], header: bool) -> String {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    if columns == 0 {
        return "<empty>\n".to_owned();
    }
    let mut widths = vec![0usize; columns];
    for row in rows {
        for (i, cell) in row.iter().enumerate() {
            let w = cell.lines().map(|l| l.chars().count()).max().unwrap_or(0);
            widths[i] = widths[i].max(w);
        }
    }
    let rule: String = widths
        .iter()
        .map(|w| format!("+{}", "-".repeat(w + 4)))
        .collect::<String>()
        + "+\n";
    let mut out = rule.clone();
    for (r, row) in rows.iter().enumerate() {
        let height = row
            .iter()
            .map(|c| c.lines().count().max(1))
            .max()
            .unwrap_or(1);
        for line in 0..height {
            for (i, w) in widths.iter().enumerate() {
                let text = row.get(i).and_then(|c| c.lines().nth(line)).unwrap_or("");
                out.push_str(&format!("|  {text:<w$}  "));
            }
            out.push_str("|\n");
        }
        if r == 0 && header {
            out.push_str(&rule);
        }
    }
    out.push_str(&rule);
    out
}

/// Assembles the report from its sections (title, body).
pub(crate) fn render(sections: &[(&str, String)]) -> String {
    let mut out = String::from(
        "\n----------------------- AimRT Initialization Report Begin ----------------------\n\n",
    );
    for (i, (title, body)) in sections.iter().enumerate() {
        out.push_str(&format!("[{}]. {title}\n{body}\n", i + 1));
    }
    out.push_str(
        "\n----------------------- AimRT Initialization Report End ------------------------\n\n",
    );
    out
}

/// `[ a , b ]`, or `<empty>`, as AimRT lists names.
pub(crate) fn list<'a>(names: impl IntoIterator<Item = &'a str>) -> String {
    let names: Vec<&str> = names.into_iter().collect();
    if names.is_empty() {
        "<empty>\n".to_owned()
    } else {
        format!("[ {} ]\n", names.join(" , "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_are_boxed_and_padded() {
        let rows = vec![
            vec!["name".to_owned(), "type".to_owned()],
            vec!["work".to_owned(), "asio_thread".to_owned()],
        ];
        assert_eq!(
            table(&rows, true),
            "+--------+---------------+\n\
             |  name  |  type         |\n\
             +--------+---------------+\n\
             |  work  |  asio_thread  |\n\
             +--------+---------------+\n"
        );
        assert_eq!(table(&[], true), "<empty>\n");
        assert_eq!(list(["a", "b"]), "[ a , b ]\n");
        assert_eq!(list([]), "<empty>\n");
    }

    #[test]
    fn sections_are_numbered() {
        let r = render(&[("Base Info", "x\n".into()), ("Plugin List", "y\n".into())]);
        assert!(r.contains("[1]. Base Info\nx\n"));
        assert!(r.contains("[2]. Plugin List\ny\n"));
        assert!(r.contains("AimRT Initialization Report End"));
    }
}
