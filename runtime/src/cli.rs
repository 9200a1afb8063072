//! `aimrt_main`'s command line, gflags style as AimRT: `--x=v`, `--x v`, `-x`, `--nox`.

use std::path::PathBuf;

use crate::Error;
use aimrt_plugin_api::__private::closest;

/// The runtime's version, as `-v` prints it.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Parsed flags.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cli {
    /// `--cfg_file_path`; empty starts with no config file.
    pub cfg_file_path: String,
    /// `--register_signal` (default true).
    pub register_signal: bool,
    /// `--running_duration` seconds; 0 runs until a signal.
    pub running_duration: i32,
    /// `--dump_cfg_file`: write the effective config after initialization.
    pub dump_cfg_file: bool,
    /// `--dump_cfg_file_path` (default `./dump_cfg.yaml`).
    pub dump_cfg_file_path: String,
    /// `--dump_init_report`: write the initialization report after initialization.
    pub dump_init_report: bool,
    /// `--dump_init_report_path` (default `./init_report.txt`).
    pub dump_init_report_path: String,
}

impl Default for Cli {
    fn default() -> Self {
        Cli {
            cfg_file_path: String::new(),
            register_signal: true,
            running_duration: 0,
            dump_cfg_file: false,
            dump_cfg_file_path: "./dump_cfg.yaml".into(),
            dump_init_report: false,
            dump_init_report_path: "./init_report.txt".into(),
        }
    }
}

impl Cli {
    /// The config path, if one was given.
    pub fn cfg_file(&self) -> Option<PathBuf> {
        (!self.cfg_file_path.is_empty()).then(|| PathBuf::from(&self.cfg_file_path))
    }

    /// Where to dump the effective config, if asked to.
    pub fn dump_cfg_file(&self) -> Option<PathBuf> {
        self.dump_cfg_file
            .then(|| PathBuf::from(&self.dump_cfg_file_path))
    }

    /// Where to dump the initialization report, if asked to.
    pub fn dump_init_report(&self) -> Option<PathBuf> {
        self.dump_init_report
            .then(|| PathBuf::from(&self.dump_init_report_path))
    }
}

/// What the command line asks for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CliAction {
    /// Print the usage and exit 0 (also when there are no arguments).
    Help,
    /// Print the version and exit 0.
    Version,
    /// Run.
    Run(Cli),
}

const BOOL_FLAGS: &[&str] = &[
    "register_signal",
    "dump_cfg_file",
    "dump_init_report",
    "help",
    "h",
    "version",
    "v",
];
const VALUE_FLAGS: &[&str] = &[
    "cfg_file_path",
    "dump_cfg_file_path",
    "dump_init_report_path",
    "running_duration",
];

/// The usage text.
pub fn usage() -> String {
    format!(
        "OVERVIEW: aimrt-rs is AimRT's runtime for robot software, in Rust.\n\n\
         VERSION: {VERSION}\n\n\
         USAGE: aimrt_main --cfg_file_path=<string> [options]\n\n\
         OPTIONS:\n\n\
         Generic Options:\n\n  \
         --version                         - Show version\n  \
         --help                            - Show help\n\n\
         AimRT Options:\n\n  \
         --cfg_file_path=<string>          - Path to the configuration file, default is empty\n  \
         --dump_cfg_file                   - Dump the configuration file to a file, default is false\n  \
         --dump_cfg_file_path=<string>     - Path to dump the configuration file, default is ./dump_cfg.yaml\n  \
         --dump_init_report                - Dump the initialization report, default is false\n  \
         --dump_init_report_path=<string>  - Path to dump the initialization report, default is ./init_report.txt\n  \
         --register_signal                 - Register signal handlers for SIGINT and SIGTERM, default is true\n  \
         --running_duration=<int>          - Running duration in seconds, default is 0 which means running forever\n"
    )
}

fn parse_bool(flag: &str, v: &str) -> Result<bool, Error> {
    match v.to_ascii_lowercase().as_str() {
        "true" | "1" | "yes" | "t" | "y" => Ok(true),
        "false" | "0" | "no" | "f" | "n" => Ok(false),
        _ => Err(Error::Cli(format!(
            "illegal value '{v}' for bool flag '--{flag}'; use true or false"
        ))),
    }
}

/// `--running_duration`: whole seconds, 0 or more.
fn parse_duration(value: &str) -> Result<i32, Error> {
    match value.trim().parse::<i32>() {
        Ok(secs) if secs >= 0 => Ok(secs),
        _ => Err(Error::Cli(format!(
            "illegal value '{value}' for flag '--running_duration'; give whole seconds from 0 (run until a signal) to {}, e.g. --running_duration=5",
            i32::MAX
        ))),
    }
}

/// Turns one argument into text, or says which one is not UTF-8.
fn utf8(arg: std::ffi::OsString, index: usize) -> Result<String, Error> {
    arg.into_string().map_err(|raw| {
        Error::Cli(format!(
            "argument {index} ({}) is not valid UTF-8; give paths and values as UTF-8 text",
            raw.to_string_lossy()
        ))
    })
}

/// Parses the arguments after the program name (`std::env::args_os().skip(1)`).
///
/// Every argument must be a flag: a positional argument, a value flag given twice, an
/// empty `--cfg_file_path` and a negative `--running_duration` are errors.
pub fn parse_args<I, A>(args: I) -> Result<CliAction, Error>
where
    I: IntoIterator<Item = A>,
    A: Into<std::ffi::OsString>,
{
    let args = args
        .into_iter()
        .enumerate()
        .map(|(i, a)| utf8(a.into(), i + 1))
        .collect::<Result<Vec<String>, Error>>()?;
    if args.is_empty() {
        return Ok(CliAction::Help);
    }
    let mut cli = Cli::default();
    let mut seen: Vec<String> = Vec::new();
    let mut it = args.into_iter();
    while let Some(arg) = it.next() {
        let Some(body) = arg.strip_prefix("--").or_else(|| arg.strip_prefix('-')) else {
            let hint = if arg.ends_with(".yaml") || arg.ends_with(".yml") {
                format!("; to run that config, write --cfg_file_path={arg}")
            } else {
                String::new()
            };
            return Err(Error::Cli(format!(
                "unexpected argument '{arg}': aimrt_main takes only flags{hint}; run aimrt_main --help for the flags"
            )));
        };
        let (name, inline) = match body.split_once('=') {
            Some((n, v)) => (n.to_owned(), Some(v.to_owned())),
            None => (body.to_owned(), None),
        };
        if BOOL_FLAGS.contains(&name.as_str()) {
            let value = match &inline {
                Some(v) => parse_bool(&name, v)?,
                None => true,
            };
            match name.as_str() {
                "help" | "h" if value => return Ok(CliAction::Help),
                "version" | "v" if value => return Ok(CliAction::Version),
                "register_signal" => cli.register_signal = value,
                "dump_cfg_file" => cli.dump_cfg_file = value,
                "dump_init_report" => cli.dump_init_report = value,
                _ => {}
            }
            continue;
        }
        if let Some(neg) = name.strip_prefix("no") {
            if BOOL_FLAGS.contains(&neg) && inline.is_none() {
                match neg {
                    "register_signal" => cli.register_signal = false,
                    "dump_cfg_file" => cli.dump_cfg_file = false,
                    "dump_init_report" => cli.dump_init_report = false,
                    _ => {}
                }
                continue;
            }
        }
        if VALUE_FLAGS.contains(&name.as_str()) {
            let value = match inline {
                Some(v) => v,
                None => it
                    .next()
                    .ok_or_else(|| Error::Cli(format!("flag '--{name}' is missing its value")))?,
            };
            if seen.contains(&name) {
                return Err(Error::Cli(format!(
                    "flag '--{name}' is given twice; give it once"
                )));
            }
            if value.is_empty() && name != "running_duration" {
                return Err(Error::Cli(format!(
                    "flag '--{name}' has an empty value; give a path, e.g. --{name}=./cfg.yaml"
                )));
            }
            match name.as_str() {
                "cfg_file_path" => cli.cfg_file_path = value,
                "dump_cfg_file_path" => cli.dump_cfg_file_path = value,
                "dump_init_report_path" => cli.dump_init_report_path = value,
                _ => cli.running_duration = parse_duration(&value)?,
            }
            seen.push(name);
            continue;
        }
        let all = || BOOL_FLAGS.iter().chain(VALUE_FLAGS).copied();
        // A close spelling, else the one flag the name begins (`--cfg_file`).
        let starting = || {
            let mut with = all().filter(|f| !name.is_empty() && f.starts_with(name.as_str()));
            with.next().filter(|_| with.next().is_none())
        };
        let hint = closest(&name, all())
            .or_else(starting)
            .map_or_else(String::new, |c| format!("; did you mean '--{c}'?"));
        return Err(Error::Cli(format!(
            "unknown command line flag '{arg}'{hint}; run aimrt_main --help for the flags"
        )));
    }
    Ok(CliAction::Run(cli))
}

/// Writes `line` and a newline to stdout. A closed or broken stdout (`aimrt_main … | head`)
/// drops the line instead of panicking, as `println!` would.
///
/// ```
/// aimrt_runtime::say(format_args!("AimRT exit."));
/// ```
pub fn say(line: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let _ = writeln!(std::io::stdout().lock(), "{line}");
}

/// [`say`] on stderr.
pub fn say_err(line: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<CliAction, Error> {
        parse_args(args.iter().map(|s| (*s).to_owned()))
    }

    #[test]
    fn gflags_forms() {
        let CliAction::Run(c) = parse(&[
            "--cfg_file_path=a.yaml",
            "--running_duration",
            "3",
            "--noregister_signal",
        ])
        .unwrap() else {
            panic!()
        };
        assert_eq!(
            c,
            Cli {
                cfg_file_path: "a.yaml".into(),
                register_signal: false,
                running_duration: 3,
                ..Cli::default()
            }
        );
        let CliAction::Run(c) =
            parse(&["-cfg_file_path", "b.yaml", "--register_signal=false"]).unwrap()
        else {
            panic!()
        };
        assert_eq!(c.cfg_file_path, "b.yaml");
        assert!(!c.register_signal);
        let CliAction::Run(c) = parse(&[
            "--dump_cfg_file",
            "--dump_cfg_file_path",
            "out.yaml",
            "--dump_init_report=true",
            "--nodump_init_report",
        ])
        .unwrap() else {
            panic!()
        };
        assert_eq!(c.dump_cfg_file(), Some(PathBuf::from("out.yaml")));
        assert_eq!(c.dump_init_report(), None);
    }

    #[test]
    fn help_version_and_empty() {
        assert_eq!(parse(&[]).unwrap(), CliAction::Help);
        assert_eq!(parse(&["-h"]).unwrap(), CliAction::Help);
        assert_eq!(parse(&["--version"]).unwrap(), CliAction::Version);
        assert_eq!(parse(&["-v"]).unwrap(), CliAction::Version);
    }

    #[test]
    fn errors_explain_themselves() {
        let e = parse(&["--cfg_file_pth=x"]).unwrap_err().to_string();
        assert!(
            e.contains(
                "unknown command line flag '--cfg_file_pth=x'; did you mean '--cfg_file_path'?"
            ),
            "{e}"
        );
        let e = parse(&["--cfg_file=x"]).unwrap_err().to_string();
        assert!(
            e.contains("'--cfg_file=x'; did you mean '--cfg_file_path'?"),
            "{e}"
        );
        // The start of two flags names neither.
        let e = parse(&["--dump_cfg=x"]).unwrap_err().to_string();
        assert!(
            e.contains("unknown command line flag '--dump_cfg=x'; run"),
            "{e}"
        );
        let e = parse(&["--running_duration=abc"]).unwrap_err().to_string();
        assert!(e.contains("whole seconds"), "{e}");
        let e = parse(&["--cfg_file_path"]).unwrap_err().to_string();
        assert!(e.contains("missing its value"), "{e}");
    }

    #[test]
    fn positional_empty_twice_and_negative_are_refused() {
        let e = parse(&["cfg.yaml"]).unwrap_err().to_string();
        assert!(e.contains("write --cfg_file_path=cfg.yaml"), "{e}");
        let e = parse(&["--cfg_file_path="]).unwrap_err().to_string();
        assert!(e.contains("empty value"), "{e}");
        let e = parse(&["--cfg_file_path=a.yaml", "--cfg_file_path", "b.yaml"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("'--cfg_file_path' is given twice"), "{e}");
        let e = parse(&["--running_duration=-1"]).unwrap_err().to_string();
        assert!(e.contains("from 0"), "{e}");
    }

    #[test]
    fn non_utf8_arguments_are_refused() {
        use std::os::unix::ffi::OsStringExt;
        let bad = std::ffi::OsString::from_vec(b"--cfg_file_path=\xff.yaml".to_vec());
        let e = parse_args([std::ffi::OsString::from("--running_duration=1"), bad])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("argument 2") && e.contains("not valid UTF-8"),
            "{e}"
        );
    }
}
