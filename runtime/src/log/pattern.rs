//! AimRT's log pattern language: `%` and one character; everything else is literal.
//!
//! | spec | meaning |
//! |---|---|
//! | `%c` | local `YYYY-mm-dd HH:MM:SS` |
//! | `%Y %m %d %H %M %S` | local year, month, day, hour, minute, second |
//! | `%D` / `%T` | `YYYY-mm-dd` / `HH:MM:SS` |
//! | `%f` | microseconds, 6 digits |
//! | `%A` / `%a` | weekday, `Tuesday` / `Tue` |
//! | `%l` | level name |
//! | `%t` | OS thread id |
//! | `%n` | logger (module) name |
//! | `%g` / `%G` | source file / its base name |
//! | `%R` | source line |
//! | `%F` | function (the Rust module path of the call site) |
//! | `%v` | message |
//! | `%x`, any other | `x` itself (`%%` is `%`); a trailing lone `%` is literal |

use std::fmt::Write as _;

use aimrt_plugin_api::LogLevel;
use chrono::{DateTime, Datelike, Local, Timelike};

/// AimRT's default line layout.
pub(crate) const DEFAULT: &str = "[%c.%f][%l][%t][%n][%g:%R @%F]%v";
/// The layout of lines written before the config is read and after shutdown.
pub(crate) const BOOTSTRAP: &str = "[%c.%f][%l][%t][%g:%R @%F]%v";

#[derive(Debug, Clone, PartialEq, Eq)]
enum Piece {
    Text(String),
    DateTime,
    Year,
    Month,
    Day,
    Hour,
    Minute,
    Second,
    Date,
    Time,
    Micros,
    Weekday,
    WeekdayShort,
    Level,
    Thread,
    Name,
    File,
    BaseName,
    Line,
    Function,
    Message,
}

/// A compiled pattern.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Pattern {
    pieces: Vec<Piece>,
}

/// Everything a pattern can show about one line.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Record<'a> {
    pub(crate) time: DateTime<Local>,
    pub(crate) level: LogLevel,
    pub(crate) thread: i32,
    pub(crate) name: &'a str,
    pub(crate) file: &'a str,
    pub(crate) line: u32,
    pub(crate) function: &'a str,
    pub(crate) message: &'a str,
}

impl Pattern {
    /// Compiles `text`; an empty pattern is refused, as in AimRT.
    pub(crate) fn parse(text: &str) -> Result<Pattern, String> {
        if text.is_empty() {
            return Err(format!(
                "the pattern is empty; leave the key out for the default '{DEFAULT}'"
            ));
        }
        let mut pieces = Vec::new();
        let mut literal = String::new();
        let mut chars = text.chars();
        while let Some(c) = chars.next() {
            if c != '%' {
                literal.push(c);
                continue;
            }
            let Some(spec) = chars.next() else {
                literal.push('%');
                break;
            };
            let piece = match spec {
                'c' => Piece::DateTime,
                'Y' => Piece::Year,
                'm' => Piece::Month,
                'd' => Piece::Day,
                'H' => Piece::Hour,
                'M' => Piece::Minute,
                'S' => Piece::Second,
                'D' => Piece::Date,
                'T' => Piece::Time,
                'f' => Piece::Micros,
                'A' => Piece::Weekday,
                'a' => Piece::WeekdayShort,
                'l' => Piece::Level,
                't' => Piece::Thread,
                'n' => Piece::Name,
                'g' => Piece::File,
                'G' => Piece::BaseName,
                'R' => Piece::Line,
                'F' => Piece::Function,
                'v' => Piece::Message,
                other => {
                    literal.push(other);
                    continue;
                }
            };
            if !literal.is_empty() {
                pieces.push(Piece::Text(std::mem::take(&mut literal)));
            }
            pieces.push(piece);
        }
        if !literal.is_empty() {
            pieces.push(Piece::Text(literal));
        }
        Ok(Pattern { pieces })
    }

    /// AimRT's default pattern.
    pub(crate) fn default_pattern() -> Pattern {
        Pattern::parse(DEFAULT).unwrap_or(Pattern { pieces: Vec::new() })
    }

    /// Appends `record` laid out by this pattern to `out` (no newline).
    pub(crate) fn format(&self, r: &Record<'_>, out: &mut String) {
        let t = &r.time;
        for piece in &self.pieces {
            // Writing to a String cannot fail.
            let _ = match piece {
                Piece::Text(s) => {
                    out.push_str(s);
                    Ok(())
                }
                Piece::DateTime => write!(
                    out,
                    "{:04}-{:02}-{:02} {:02}:{:02}:{:02}",
                    t.year(),
                    t.month(),
                    t.day(),
                    t.hour(),
                    t.minute(),
                    t.second()
                ),
                Piece::Year => write!(out, "{:04}", t.year()),
                Piece::Month => write!(out, "{:02}", t.month()),
                Piece::Day => write!(out, "{:02}", t.day()),
                Piece::Hour => write!(out, "{:02}", t.hour()),
                Piece::Minute => write!(out, "{:02}", t.minute()),
                Piece::Second => write!(out, "{:02}", t.second()),
                Piece::Date => write!(out, "{:04}-{:02}-{:02}", t.year(), t.month(), t.day()),
                Piece::Time => write!(out, "{:02}:{:02}:{:02}", t.hour(), t.minute(), t.second()),
                // A leap second shows as 999999, never as 7 digits.
                Piece::Micros => write!(out, "{:06}", (t.nanosecond() / 1000).min(999_999)),
                Piece::Weekday => write!(out, "{}", weekday_name(t.weekday())),
                Piece::WeekdayShort => write!(out, "{}", t.weekday()),
                Piece::Level => write!(out, "{}", r.level),
                Piece::Thread => write!(out, "{}", r.thread),
                Piece::Name => {
                    out.push_str(r.name);
                    Ok(())
                }
                Piece::File => {
                    out.push_str(source_path(r.file));
                    Ok(())
                }
                Piece::BaseName => {
                    out.push_str(r.file.rsplit(['/', '\\']).next().unwrap_or(r.file));
                    Ok(())
                }
                Piece::Line => write!(out, "{}", r.line),
                Piece::Function => {
                    out.push_str(r.function);
                    Ok(())
                }
                Piece::Message => {
                    push_message(out, r.message);
                    Ok(())
                }
            };
        }
    }
}

fn weekday_name(day: chrono::Weekday) -> &'static str {
    use chrono::Weekday::*;
    match day {
        Mon => "Monday",
        Tue => "Tuesday",
        Wed => "Wednesday",
        Thu => "Thursday",
        Fri => "Friday",
        Sat => "Saturday",
        Sun => "Sunday",
    }
}

/// A message as `%v` shows it: a dependency's source path in its text (zenoh's errors end
/// in ` at /root/.cargo/registry/src/index.crates.io-…/zenoh-link-commons-1.10.2/src/tcp.rs:61`)
/// shortened as `%g` shortens it; any other text as it is.
fn push_message(out: &mut String, message: &str) {
    const REGISTRY: &str = "/registry/src/";
    let mut rest = message;
    while let Some(at) = rest.find(REGISTRY) {
        // The path starts after the last space, quote or bracket before the marker.
        let start = rest[..at]
            .rfind(|c: char| c.is_whitespace() || matches!(c, '(' | '[' | '\'' | '"' | '`'))
            .map_or(0, |i| i + 1);
        let after = &rest[at + REGISTRY.len()..];
        let Some((_, crate_path)) = after.split_once('/') else {
            break;
        };
        out.push_str(&rest[..start]);
        rest = crate_path;
    }
    out.push_str(rest);
}

/// A call site's file as `%g` shows it. Our crates' paths are relative to the workspace
/// (`runtime/src/log/mod.rs`); a dependency's are absolute paths into cargo's registry
/// (`/root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/zenoh-1.10.2/src/…`),
/// shown from the crate's folder on (`zenoh-1.10.2/src/…`).
fn source_path(file: &str) -> &str {
    const REGISTRY: &str = "/registry/src/";
    match file.find(REGISTRY) {
        // The index's folder, then the crate's.
        Some(at) => file[at + REGISTRY.len()..]
            .split_once('/')
            .map_or(file, |(_, crate_path)| crate_path),
        None => file,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use chrono::TimeZone;

    #[test]
    fn a_dependencys_source_path_in_a_message_is_shown_from_its_crate() {
        let mut out = String::new();
        push_message(&mut out, "Unable to open listener tcp/127.0.0.1:7448: [127.0.0.1:7448: Address already in use (os error 98) at /root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/zenoh-link-commons-1.10.2/src/tcp.rs:61.]");
        assert_eq!(out, "Unable to open listener tcp/127.0.0.1:7448: [127.0.0.1:7448: Address already in use (os error 98) at zenoh-link-commons-1.10.2/src/tcp.rs:61.]");
        for plain in ["no path here", "a/registry/src/ without a crate folder", ""] {
            let mut out = String::new();
            push_message(&mut out, plain);
            assert_eq!(out, plain);
        }
    }

    fn record() -> Record<'static> {
        Record {
            time: Local
                .with_ymd_and_hms(2024, 10, 1, 10, 10, 10)
                .unwrap()
                .with_nanosecond(12_345_000)
                .unwrap(),
            level: LogLevel::Info,
            thread: 1234,
            name: "test_module",
            file: "XX/YY/ZZ/test_file.rs",
            line: 20,
            function: "test_function",
            message: "test log message",
        }
    }

    fn render(pattern: &str) -> String {
        let mut out = String::new();
        Pattern::parse(pattern).unwrap().format(&record(), &mut out);
        out
    }

    #[test]
    fn default_pattern_matches_aimrt_example() {
        assert_eq!(
            render(DEFAULT),
            "[2024-10-01 10:10:10.012345][Info][1234][test_module][XX/YY/ZZ/test_file.rs:20 @test_function]test log message"
        );
    }

    #[test]
    fn every_specifier() {
        assert_eq!(render("%Y|%m|%d|%H|%M|%S"), "2024|10|01|10|10|10");
        assert_eq!(render("%D %T"), "2024-10-01 10:10:10");
        assert_eq!(render("%A %a"), "Tuesday Tue");
        assert_eq!(render("%G:%R"), "test_file.rs:20");
        assert_eq!(
            render("%l %t %n %F %v"),
            "Info 1234 test_module test_function test log message"
        );
    }

    #[test]
    fn a_dependencys_file_is_shown_from_its_crate_folder() {
        let mut r = record();
        r.file = "/root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/zenoh-1.10.2/src/net/runtime/orchestrator.rs";
        let mut out = String::new();
        Pattern::parse("%g|%G").unwrap().format(&r, &mut out);
        assert_eq!(
            out,
            "zenoh-1.10.2/src/net/runtime/orchestrator.rs|orchestrator.rs"
        );
        // Our own files, and anything else, as they are.
        assert_eq!(
            source_path("runtime/src/log/mod.rs"),
            "runtime/src/log/mod.rs"
        );
        assert_eq!(
            source_path("/x/registry/src/no-slash"),
            "/x/registry/src/no-slash"
        );
    }

    #[test]
    fn unknown_specifiers_and_trailing_percent_are_literal() {
        assert_eq!(render("100%% %q%"), "100% q%");
        assert_eq!(render("plain"), "plain");
    }

    #[test]
    fn empty_pattern_is_refused() {
        assert!(Pattern::parse("").unwrap_err().contains("empty"));
    }
}
