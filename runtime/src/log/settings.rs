//! `aimrt.log`, validated: levels, and each backend's options with AimRT's keys and defaults.

use std::path::PathBuf;
use std::time::Duration;

use aimrt_plugin_api::LogLevel;
use regex::Regex;
use serde::{Deserialize, Serialize};

use super::pattern::Pattern;
use crate::config::{Config, Located};
use crate::error::Error;

/// The backend types this runtime writes.
pub(crate) const BACKEND_TYPES: [&str; 2] = ["console", "rotate_file"];

/// A validated `aimrt.log` section.
#[derive(Debug)]
pub(crate) struct LogSettings {
    pub(crate) core_lvl: LogLevel,
    pub(crate) module_lvl: LogLevel,
    pub(crate) backends: Vec<BackendSettings>,
    /// Accepted-but-ignored keys and similar notes, one line each, for the log.
    pub(crate) warnings: Vec<String>,
}

/// One backend: what it writes to, and which lines in which layout.
#[derive(Debug)]
pub(crate) struct BackendSettings {
    pub(crate) kind: BackendKind,
    pub(crate) pattern: Pattern,
    /// `None` for the default `(.*)`: every logger.
    pub(crate) module_filter: Option<Regex>,
    /// `file:line:col` of the backend's `type`.
    pub(crate) at: String,
}

/// A backend's own options.
#[derive(Debug, Clone)]
pub(crate) enum BackendKind {
    Console {
        color: bool,
    },
    RotateFile(RotateFileOptions),
    /// A type a plugin may register (ABI 1.10), checked once plugins are loaded: its
    /// options less the keys the runtime reads, as JSON, and where they are.
    Plugin {
        type_name: String,
        options_json: String,
        location: String,
    },
}

impl BackendKind {
    pub(crate) fn type_name(&self) -> &str {
        match self {
            BackendKind::Console { .. } => "console",
            BackendKind::RotateFile(_) => "rotate_file",
            BackendKind::Plugin { type_name, .. } => type_name,
        }
    }
}

/// The keys of a plugin backend's options that the runtime reads (as for `console`),
/// taken out of `json` (an object, or null for none); the rest stays for the plugin.
fn common_of(json: &str) -> Result<(Common, String), String> {
    let value = serde_json::from_str(json).map_err(|e| e.to_string())?;
    common_from(value).map(|(common, rest)| (common, serde_json::Value::Object(rest).to_string()))
}

/// The keys the runtime reads of a backend's options, and the rest.
fn common_from(
    options: serde_json::Value,
) -> Result<(Common, serde_json::Map<String, serde_json::Value>), String> {
    let mut map = match options {
        serde_json::Value::Object(m) => m,
        serde_json::Value::Null => serde_json::Map::new(),
        other => return Err(format!("options must be a map, found {other}")),
    };
    let mut take = |key: &str| -> Result<Option<String>, String> {
        match map.remove(key) {
            None | Some(serde_json::Value::Null) => Ok(None),
            Some(serde_json::Value::String(s)) => Ok(Some(s)),
            Some(other) => Err(format!("'{key}' must be text, found {other}")),
        }
    };
    let common = Common {
        module_filter: take("module_filter")?,
        pattern: take("pattern")?,
        log_executor_name: take("log_executor_name")?,
    };
    Ok((common, map))
}

/// The options of a plugin's backend as `--dump_cfg_file` writes them: what its factory
/// `reported` reading, with the keys the runtime reads taken from `written`
/// (`module_filter` and `pattern` with their defaults, `log_executor_name` where set).
pub(crate) fn plugin_options_as_read(
    written: Option<&serde_json::Value>,
    reported: &serde_json::Value,
) -> serde_json::Value {
    // The written options passed validation at start-up; a failure here keeps defaults.
    let written = written.cloned().unwrap_or_default();
    let common = common_from(written).map_or_else(|_| Common::default(), |(c, _)| c);
    let mut out = match reported {
        serde_json::Value::Object(m) => m.clone(),
        _ => serde_json::Map::new(),
    };
    let filter = common.module_filter.unwrap_or_else(|| "(.*)".to_owned());
    let pattern = common
        .pattern
        .unwrap_or_else(|| super::pattern::DEFAULT.to_owned());
    out.insert("module_filter".to_owned(), filter.into());
    out.insert("pattern".to_owned(), pattern.into());
    if let Some(name) = common.log_executor_name {
        out.insert("log_executor_name".to_owned(), name.into());
    }
    serde_json::Value::Object(out)
}

/// `rotate_file` options after validation.
#[derive(Debug, Clone)]
pub(crate) struct RotateFileOptions {
    pub(crate) path: PathBuf,
    pub(crate) filename: String,
    pub(crate) max_file_size: u64,
    pub(crate) max_file_num: u32,
    /// `Some((executor, interval))` when `enable_sync` is true.
    pub(crate) sync: Option<(String, Duration)>,
    pub(crate) suffix_with_timestamp: bool,
}

const MIB: u64 = 1024 * 1024;

/// The keys every backend has.
#[derive(Default)]
struct Common {
    module_filter: Option<String>,
    pattern: Option<String>,
    /// Documented by AimRT, ignored by its code; accepted with a warning.
    log_executor_name: Option<String>,
}

#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ConsoleOptions {
    #[serde(default = "yes")]
    color: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    module_filter: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pattern: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    log_executor_name: Option<String>,
}

#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RotateFileConfig {
    #[serde(default = "default_path")]
    path: String,
    #[serde(default = "default_filename")]
    filename: String,
    #[serde(default = "default_max_file_size_m")]
    max_file_size_m: u32,
    #[serde(default = "default_max_file_num")]
    max_file_num: u32,
    #[serde(default)]
    enable_sync: bool,
    #[serde(default = "default_sync_interval_ms")]
    sync_interval_ms: u32,
    #[serde(default)]
    sync_executor_name: String,
    #[serde(default = "yes")]
    suffix_with_timestamp: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    module_filter: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pattern: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    log_executor_name: Option<String>,
}

/// A log backend's `options` as `--dump_cfg_file` writes them: those of `console` and
/// `rotate_file` with every key filled in (`module_filter` `(.*)` and the default
/// `pattern` where not set), anything else (a type or options that do not read) as
/// written.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub(crate) enum NormalOptions<'a> {
    Console(ConsoleOptions),
    RotateFile(RotateFileConfig),
    AsWritten(Option<&'a serde_json::Value>),
}

impl<'a> NormalOptions<'a> {
    pub(crate) fn of(type_name: &str, options: Option<&'a serde_json::Value>) -> Self {
        let none = serde_json::Value::Object(serde_json::Map::new());
        let written = match options {
            None | Some(serde_json::Value::Null) => &none,
            Some(o) => o,
        };
        let fill = |filter: &mut Option<String>, pattern: &mut Option<String>| {
            filter.get_or_insert_with(|| "(.*)".to_owned());
            pattern.get_or_insert_with(|| super::pattern::DEFAULT.to_owned());
        };
        match type_name {
            "console" => match ConsoleOptions::deserialize(written) {
                Ok(mut o) => {
                    fill(&mut o.module_filter, &mut o.pattern);
                    NormalOptions::Console(o)
                }
                Err(_) => NormalOptions::AsWritten(options),
            },
            "rotate_file" => match RotateFileConfig::deserialize(written) {
                Ok(mut o) => {
                    fill(&mut o.module_filter, &mut o.pattern);
                    NormalOptions::RotateFile(o)
                }
                Err(_) => NormalOptions::AsWritten(options),
            },
            _ => NormalOptions::AsWritten(options),
        }
    }
}

fn yes() -> bool {
    true
}
fn default_path() -> String {
    "./log".to_owned()
}
fn default_filename() -> String {
    "aimrt.log".to_owned()
}
fn default_max_file_size_m() -> u32 {
    16
}
fn default_max_file_num() -> u32 {
    100
}
fn default_sync_interval_ms() -> u32 {
    30_000
}

impl LogSettings {
    /// Validates `aimrt.log`; an absent section means no backend (lines below Warn are discarded).
    pub(crate) fn from_config(config: &Config) -> Result<LogSettings, Error> {
        let mut settings = LogSettings {
            core_lvl: LogLevel::Info,
            module_lvl: LogLevel::Info,
            backends: Vec::new(),
            warnings: Vec::new(),
        };
        let Some(log) = config.aimrt.log.as_ref() else {
            return Ok(settings);
        };
        let level = |l: &Located<String>, key: &str| {
            l.value
                .parse::<LogLevel>()
                .map_err(|e| config.error(l, format!("aimrt.log.{key}: {e}")))
        };
        settings.core_lvl = level(&log.core_lvl, "core_lvl")?;
        settings.module_lvl = level(&log.default_module_lvl, "default_module_lvl")?;
        if log.enable_crash_log {
            settings.warnings.push(format!(
                "{}: aimrt.log.enable_crash_log is accepted but ignored: panics are always logged with their location",
                config.file
            ));
        }
        for (i, entry) in log.backends.iter().enumerate() {
            let ty = &entry.type_name;
            let what = format!("aimrt.log.backends[{i}]");
            let (json, at) = config.options_of(entry.options.as_ref(), ty);
            let options_error = |e: aimrt_plugin_api::Error| Error::Config {
                file: config.file.clone(),
                line: entry.options.as_ref().map_or(ty.line, |o| o.line),
                column: entry.options.as_ref().map_or(ty.column, |o| o.column),
                message: e.to_string(),
                detail: String::new(),
            };
            let read = |kind: &str| {
                let what = format!("{what} ({kind}) options");
                move || what
            };
            let (kind, common) = match ty.value.as_str() {
                "console" => {
                    if settings
                        .backends
                        .iter()
                        .any(|b| matches!(b.kind, BackendKind::Console { .. }))
                    {
                        return Err(config.error(
                            ty,
                            format!("{what}: a second 'console' backend; console may be listed once (rotate_file may repeat)"),
                        ));
                    }
                    let o: ConsoleOptions =
                        aimrt_plugin_api::__private::read_options(&json, read("console"))
                            .map_err(options_error)?;
                    (
                        BackendKind::Console { color: o.color },
                        Common {
                            module_filter: o.module_filter,
                            pattern: o.pattern,
                            log_executor_name: o.log_executor_name,
                        },
                    )
                }
                "rotate_file" => {
                    let o: RotateFileConfig =
                        aimrt_plugin_api::__private::read_options(&json, read("rotate_file"))
                            .map_err(options_error)?;
                    let bad = |message: String| Error::Config {
                        file: config.file.clone(),
                        line: entry.options.as_ref().map_or(ty.line, |o| o.line),
                        column: entry.options.as_ref().map_or(ty.column, |o| o.column),
                        message: format!("{what} (rotate_file) options: {message}"),
                        detail: String::new(),
                    };
                    if o.filename.is_empty() || o.filename.contains('/') {
                        return Err(bad(format!(
                            "filename '{}' must be a plain file name; put the directory in 'path'",
                            o.filename
                        )));
                    }
                    if o.max_file_size_m == 0 {
                        return Err(bad(
                            "max_file_size_m is 0; give the size in MiB at which the file rotates (at least 1; default 16)".to_owned(),
                        ));
                    }
                    let sync = if o.enable_sync {
                        if o.sync_executor_name.is_empty() {
                            return Err(bad("enable_sync is true but sync_executor_name is not set; name an executor that supports timers (e.g. an asio_thread)".to_owned()));
                        }
                        if o.sync_interval_ms == 0 {
                            return Err(bad("sync_interval_ms is 0; give the fsync period in milliseconds (at least 1; default 30000)".to_owned()));
                        }
                        Some((
                            o.sync_executor_name,
                            Duration::from_millis(u64::from(o.sync_interval_ms)),
                        ))
                    } else {
                        None
                    };
                    (
                        BackendKind::RotateFile(RotateFileOptions {
                            path: PathBuf::from(o.path),
                            filename: o.filename,
                            max_file_size: u64::from(o.max_file_size_m) * MIB,
                            max_file_num: o.max_file_num,
                            sync,
                            suffix_with_timestamp: o.suffix_with_timestamp,
                        }),
                        Common {
                            module_filter: o.module_filter,
                            pattern: o.pattern,
                            log_executor_name: o.log_executor_name,
                        },
                    )
                }
                other => {
                    let (common, options_json) =
                        common_of(&json).map_err(|message| Error::Config {
                            file: config.file.clone(),
                            line: entry.options.as_ref().map_or(ty.line, |o| o.line),
                            column: entry.options.as_ref().map_or(ty.column, |o| o.column),
                            message: format!("{what} ({other}) options: {message}"),
                            detail: String::new(),
                        })?;
                    let kind = BackendKind::Plugin {
                        type_name: other.to_owned(),
                        options_json,
                        location: at.clone(),
                    };
                    (kind, common)
                }
            };
            let bad_common = |message: String| Error::Config {
                file: config.file.clone(),
                line: entry.options.as_ref().map_or(ty.line, |o| o.line),
                column: entry.options.as_ref().map_or(ty.column, |o| o.column),
                message: format!("{what} ({}) options: {message}", kind.type_name()),
                detail: String::new(),
            };
            let pattern = match common.pattern {
                Some(p) => Pattern::parse(&p).map_err(bad_common)?,
                None => Pattern::default_pattern(),
            };
            let module_filter = match common.module_filter.as_deref() {
                None | Some("(.*)") | Some(".*") => None,
                Some(f) => Some(aimrt_plugin_api::whole_match(f).map_err(|e| {
                    bad_common(format!("module_filter '{f}' is not a valid regex: {e}"))
                })?),
            };
            if let BackendKind::RotateFile(o) = &kind {
                let file = same_file_key(&o.path.join(&o.filename));
                let clash = settings.backends.iter().position(|b| {
                    matches!(&b.kind, BackendKind::RotateFile(p) if same_file_key(&p.path.join(&p.filename)) == file)
                });
                if let Some(first) = clash {
                    return Err(config.error(
                        ty,
                        format!(
                            "{what}: rotate_file writes '{}', as aimrt.log.backends[{first}] already does; every line would be written twice: give each rotate_file its own path or filename",
                            o.path.join(&o.filename).display()
                        ),
                    ));
                }
            }
            if let Some(name) = common.log_executor_name {
                settings.warnings.push(format!(
                    "{at}: {what}.options.log_executor_name '{name}' is accepted but ignored: lines are written by the log thread"
                ));
            }
            settings.backends.push(BackendSettings {
                kind,
                pattern,
                module_filter,
                at: config.at(ty),
            });
        }
        if settings.backends.is_empty() {
            settings.warnings.push(format!(
                "{}: no log backend configured (aimrt.log.backends); lines below Warn are discarded, warnings and errors go to stderr",
                config.file
            ));
        }
        Ok(settings)
    }
}

/// A path with `.` components removed, so `./log/a.log` and `log/a.log` compare equal.
fn same_file_key(path: &std::path::Path) -> PathBuf {
    path.components()
        .filter(|c| !matches!(c, std::path::Component::CurDir))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(text: &str) -> Result<LogSettings, String> {
        let config = Config::parse("cfg.yaml", text, |_| None).map_err(|e| e.to_string())?;
        LogSettings::from_config(&config).map_err(|e| e.to_string())
    }

    #[test]
    fn defaults_follow_aimrt() {
        let s = settings(
            "aimrt:\n  log:\n    backends:\n      - type: console\n      - type: rotate_file\n",
        )
        .unwrap();
        assert_eq!((s.core_lvl, s.module_lvl), (LogLevel::Info, LogLevel::Info));
        assert!(matches!(
            s.backends[0].kind,
            BackendKind::Console { color: true }
        ));
        let BackendKind::RotateFile(r) = &s.backends[1].kind else {
            panic!("not rotate_file")
        };
        assert_eq!(r.path, PathBuf::from("./log"));
        assert_eq!(r.filename, "aimrt.log");
        assert_eq!(r.max_file_size, 16 * MIB);
        assert_eq!(r.max_file_num, 100);
        assert!(r.sync.is_none() && r.suffix_with_timestamp);
        assert_eq!(s.backends[1].pattern, Pattern::default_pattern());
        assert!(s.backends[1].module_filter.is_none());
        assert!(s.warnings.is_empty());
    }

    #[test]
    fn no_backend_warns() {
        let s = settings("aimrt:\n  log:\n    core_lvl: trace\n").unwrap();
        assert_eq!(s.core_lvl, LogLevel::Trace);
        assert!(s.warnings[0].contains("no log backend"), "{:?}", s.warnings);
    }

    #[test]
    fn mistakes_are_explained() {
        for (text, expected) in [
            ("aimrt:\n  log:\n    core_lvl: loud\n", "cfg.yaml:3:15: aimrt.log.core_lvl: unknown log level 'loud'"),
            ("aimrt:\n  log:\n    backends:\n      - type: udp_lines\n        options: {pattern: 7}\n", "cfg.yaml:5:18: aimrt.log.backends[0] (udp_lines) options: 'pattern' must be text, found 7"),
            ("aimrt:\n  log:\n    backends:\n      - type: console\n      - type: console\n", "a second 'console' backend"),
            ("aimrt:\n  log:\n    backends:\n      - type: console\n        options: {colour: false}\n", "unknown key 'colour'; did you mean 'color'?"),
            ("aimrt:\n  log:\n    backends:\n      - type: console\n        options: {pattern: ''}\n", "the pattern is empty"),
            ("aimrt:\n  log:\n    backends:\n      - type: console\n        options: {module_filter: '(a'}\n", "module_filter '(a' is not a valid regex"),
            ("aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {enable_sync: true}\n", "sync_executor_name is not set"),
            ("aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {max_file_size_m: 0}\n", "max_file_size_m is 0"),
            ("aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {max_file_num: -1}\n", "max_file_num"),
            ("aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: {filename: a/b.log}\n", "plain file name"),
            ("aimrt:\n  log:\n    backends:\n      - type: rotate_file\n        options: [1]\n", "expected a map"),
        ] {
            let err = settings(text).unwrap_err();
            assert!(err.contains(expected), "{text}\n→ {err}");
            assert!(err.starts_with("cfg.yaml:"), "{err}");
        }
    }

    /// A type no built-in backend has is left for the plugins (checked once they are
    /// loaded): the runtime keeps `module_filter` and `pattern` and hands on the rest.
    #[test]
    fn another_type_keeps_its_own_options_for_a_plugin() {
        let s = settings("aimrt:\n  log:\n    backends:\n      - type: udp_lines\n        options: {address: '127.0.0.1:9', module_filter: 'Log.*', pattern: '%v'}\n").unwrap();
        let b = &s.backends[0];
        let BackendKind::Plugin {
            type_name,
            options_json,
            location,
        } = &b.kind
        else {
            panic!("{:?}", b.kind)
        };
        assert_eq!(type_name, "udp_lines");
        assert_eq!(options_json, r#"{"address":"127.0.0.1:9"}"#);
        assert_eq!(location, "cfg.yaml:5:18");
        assert!(b.module_filter.as_ref().unwrap().is_match("LoggerModule"));
        assert_ne!(b.pattern, Pattern::default_pattern());
    }

    #[test]
    fn module_filter_is_a_full_match() {
        let s = settings("aimrt:\n  log:\n    backends:\n      - type: console\n        options: {module_filter: 'Log.*|core'}\n").unwrap();
        let f = s.backends[0].module_filter.as_ref().unwrap();
        assert!(f.is_match("LoggerModule") && f.is_match("core"));
        assert!(!f.is_match("MyLoggerModule") && !f.is_match("core2"));
    }

    #[test]
    fn ignored_keys_warn() {
        let s = settings("aimrt:\n  log:\n    enable_crash_log: true\n    backends:\n      - type: rotate_file\n        options: {log_executor_name: x}\n").unwrap();
        assert_eq!(s.warnings.len(), 2, "{:?}", s.warnings);
        assert!(s.warnings[1].contains("log_executor_name 'x' is accepted but ignored"));
    }
}
