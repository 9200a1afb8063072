//! The YAML config: AimRT's key names byte for byte, typed, with line/column errors.

mod env;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_saphyr::Spanned;

use crate::Error;
use aimrt_plugin_api::__private::explain;

/// A config node with the place it was written.
#[derive(Debug, Clone)]
pub(crate) struct Located<T> {
    pub(crate) value: T,
    pub(crate) line: u64,
    pub(crate) column: u64,
}

impl<'de, T: Deserialize<'de>> Deserialize<'de> for Located<T> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = Spanned::<T>::deserialize(d)?;
        Ok(Located {
            line: s.referenced.line(),
            column: s.referenced.column(),
            value: s.value,
        })
    }
}

/// The whole file.
#[derive(Debug, Default, Deserialize)]
struct Document {
    #[serde(default)]
    aimrt: Option<Aimrt>,
}

/// `aimrt:`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Aimrt {
    #[serde(default)]
    pub(crate) configurator: Option<Configurator>,
    #[serde(default)]
    pub(crate) plugin: Option<PluginSection>,
    #[serde(default)]
    pub(crate) main_thread: Option<ThreadSection>,
    #[serde(default)]
    pub(crate) guard_thread: Option<GuardThreadSection>,
    #[serde(default)]
    pub(crate) executor: Option<ExecutorSection>,
    #[serde(default)]
    pub(crate) log: Option<LogSection>,
    #[serde(default)]
    pub(crate) module: Option<ModuleSection>,
    #[serde(default)]
    pub(crate) channel: Option<ChannelSection>,
    #[serde(default)]
    pub(crate) rpc: Option<RpcSection>,
    #[serde(default)]
    pub(crate) parameter: Option<serde_json::Value>,
    #[serde(default)]
    pub(crate) allocator: Option<serde_json::Value>,
}

/// `aimrt.configurator`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Configurator {
    #[serde(default = "default_temp_cfg_path")]
    pub(crate) temp_cfg_path: String,
}

fn default_temp_cfg_path() -> String {
    "./cfg/tmp".to_owned()
}

/// `aimrt.plugin`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PluginSection {
    #[serde(default)]
    pub(crate) plugins: Vec<PluginEntry>,
}

/// `aimrt.plugin.plugins[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PluginEntry {
    pub(crate) name: Located<String>,
    pub(crate) path: Located<String>,
    #[serde(default)]
    pub(crate) options: Option<Located<serde_json::Value>>,
}

/// `aimrt.main_thread`
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ThreadSection {
    #[serde(default = "default_main_name")]
    pub(crate) name: String,
    #[serde(default)]
    pub(crate) thread_sched_policy: String,
    #[serde(default)]
    pub(crate) thread_bind_cpu: Vec<u32>,
    /// aimrt-rs extension: a refused thread setting is an error instead of a warning.
    #[serde(default)]
    pub(crate) thread_policy_strict: bool,
}

impl ThreadSection {
    pub(crate) fn settings(&self) -> aimrt_plugin_api::ThreadSettingsRef<'_> {
        aimrt_plugin_api::ThreadSettingsRef {
            name: &self.name,
            sched_policy: &self.thread_sched_policy,
            bind_cpu: &self.thread_bind_cpu,
            strict: self.thread_policy_strict,
        }
    }
}

fn default_main_name() -> String {
    "aimrt_main".to_owned()
}

impl Default for ThreadSection {
    fn default() -> Self {
        ThreadSection {
            name: default_main_name(),
            thread_sched_policy: String::new(),
            thread_bind_cpu: Vec::new(),
            thread_policy_strict: false,
        }
    }
}

/// `aimrt.guard_thread`
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct GuardThreadSection {
    #[serde(default = "default_guard_name")]
    pub(crate) name: String,
    #[serde(default)]
    pub(crate) thread_sched_policy: String,
    #[serde(default)]
    pub(crate) thread_bind_cpu: Vec<u32>,
    /// aimrt-rs extension: a refused thread setting is an error instead of a warning.
    #[serde(default)]
    pub(crate) thread_policy_strict: bool,
    #[serde(default = "default_queue_threshold")]
    pub(crate) queue_threshold: u32,
    #[serde(default = "default_alarm_interval")]
    pub(crate) threshold_alarm_interval_ms: i32,
}

impl GuardThreadSection {
    pub(crate) fn settings(&self) -> aimrt_plugin_api::ThreadSettingsRef<'_> {
        aimrt_plugin_api::ThreadSettingsRef {
            name: &self.name,
            sched_policy: &self.thread_sched_policy,
            bind_cpu: &self.thread_bind_cpu,
            strict: self.thread_policy_strict,
        }
    }
}

fn default_guard_name() -> String {
    "aimrt_guard".to_owned()
}
fn default_queue_threshold() -> u32 {
    10_000
}
fn default_alarm_interval() -> i32 {
    1000
}

impl Default for GuardThreadSection {
    fn default() -> Self {
        GuardThreadSection {
            name: default_guard_name(),
            thread_sched_policy: String::new(),
            thread_bind_cpu: Vec::new(),
            thread_policy_strict: false,
            queue_threshold: default_queue_threshold(),
            threshold_alarm_interval_ms: default_alarm_interval(),
        }
    }
}

/// `aimrt.executor`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ExecutorSection {
    #[serde(default)]
    pub(crate) executors: Vec<ExecutorEntry>,
    /// aimrt-rs extension: how long shutdown waits for one executor's threads.
    #[serde(default = "default_join_timeout_ms")]
    pub(crate) join_timeout_ms: u64,
}

fn default_join_timeout_ms() -> u64 {
    5000
}

/// `aimrt.executor.executors[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ExecutorEntry {
    pub(crate) name: Located<String>,
    #[serde(rename = "type")]
    pub(crate) type_name: Located<String>,
    #[serde(default)]
    pub(crate) options: Option<Located<serde_json::Value>>,
}

/// `aimrt.log`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct LogSection {
    #[serde(default = "default_level")]
    pub(crate) core_lvl: Located<String>,
    #[serde(default = "default_level")]
    pub(crate) default_module_lvl: Located<String>,
    #[serde(default)]
    pub(crate) enable_crash_log: bool,
    #[serde(default)]
    pub(crate) backends: Vec<LogBackendEntry>,
}

fn default_level() -> Located<String> {
    Located {
        value: "Info".to_owned(),
        line: 0,
        column: 0,
    }
}

/// `aimrt.log.backends[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct LogBackendEntry {
    #[serde(rename = "type")]
    pub(crate) type_name: Located<String>,
    #[serde(default)]
    pub(crate) options: Option<Located<serde_json::Value>>,
}

/// `aimrt.rpc`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RpcSection {
    #[serde(default)]
    pub(crate) backends: Vec<BackendEntry>,
    #[serde(default)]
    pub(crate) clients_options: Vec<RpcFuncOptions>,
    #[serde(default)]
    pub(crate) servers_options: Vec<RpcFuncOptions>,
}

/// `aimrt.rpc.backends[i]` and `aimrt.channel.backends[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct BackendEntry {
    #[serde(rename = "type")]
    pub(crate) type_name: Located<String>,
    #[serde(default)]
    pub(crate) options: Option<Located<serde_json::Value>>,
}

/// `aimrt.rpc.servers_options[i]` / `clients_options[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RpcFuncOptions {
    pub(crate) func_name: Located<String>,
    pub(crate) enable_backends: Vec<Located<String>>,
    #[serde(default)]
    pub(crate) enable_filters: Vec<Located<String>>,
}

/// `aimrt.channel`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ChannelSection {
    #[serde(default)]
    pub(crate) backends: Vec<BackendEntry>,
    #[serde(default)]
    pub(crate) pub_topics_options: Vec<TopicOptions>,
    #[serde(default)]
    pub(crate) sub_topics_options: Vec<TopicOptions>,
}

/// `aimrt.channel.pub_topics_options[i]` / `sub_topics_options[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct TopicOptions {
    pub(crate) topic_name: Located<String>,
    pub(crate) enable_backends: Vec<Located<String>>,
    #[serde(default)]
    pub(crate) enable_filters: Vec<Located<String>>,
}

/// `aimrt.module`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ModuleSection {
    #[serde(default)]
    pub(crate) pkgs: Vec<PkgEntry>,
    #[serde(default)]
    pub(crate) modules: Vec<ModuleEntry>,
}

/// `aimrt.module.pkgs[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PkgEntry {
    pub(crate) path: Located<String>,
    #[serde(default)]
    pub(crate) enable_modules: Vec<Located<String>>,
    #[serde(default)]
    pub(crate) disable_modules: Vec<Located<String>>,
}

/// `aimrt.module.modules[i]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ModuleEntry {
    pub(crate) name: Located<String>,
    #[serde(default = "default_true")]
    pub(crate) enable: bool,
    #[serde(default)]
    pub(crate) log_lvl: Option<Located<String>>,
    #[serde(default)]
    pub(crate) cfg_file_path: String,
}

fn default_true() -> bool {
    true
}

/// A loaded config: the typed `aimrt` tree plus every other root node (module configs).
#[derive(Debug, Default)]
pub(crate) struct Config {
    /// The file, as given (for messages); empty when started without one.
    pub(crate) file: String,
    pub(crate) aimrt: Aimrt,
    pub(crate) roots: BTreeMap<String, serde_json::Value>,
    /// The text after `${VAR}` substitution: the effective config, as `--dump_cfg_file`
    /// writes it.
    pub(crate) text: String,
}

impl Config {
    /// Reads, substitutes `${VAR}`s, parses and type-checks `path`.
    pub(crate) fn load(path: &Path) -> Result<Config, Error> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::ConfigRead {
            path: path.to_owned(),
            source,
        })?;
        Config::parse(&path.display().to_string(), &text, |k| {
            std::env::var(k).ok()
        })
    }

    /// Parses config text; `file` is used in messages.
    pub(crate) fn parse(
        file: &str,
        text: &str,
        env: impl Fn(&str) -> Option<String>,
    ) -> Result<Config, Error> {
        let text = env::substitute(text, env).map_err(|u| Error::Config {
            file: file.to_owned(),
            line: u.line as u64,
            column: u.column as u64,
            message: format!(
                "environment variable '{}' is not set; set it, or write ${{{}:-default}} to give a default",
                u.name, u.name
            ),
            detail: String::new(),
        })?;
        let doc: Document = serde_saphyr::from_str(&text).map_err(|e| yaml_error(file, &e))?;
        let roots: BTreeMap<String, serde_json::Value> = if text.trim().is_empty() {
            BTreeMap::new()
        } else {
            match serde_saphyr::from_str::<Option<BTreeMap<String, serde_json::Value>>>(&text) {
                Ok(r) => r.unwrap_or_default(),
                Err(e) => return Err(yaml_error(file, &e)),
            }
        };
        Ok(Config {
            file: file.to_owned(),
            aimrt: doc.aimrt.unwrap_or_default(),
            roots,
            text,
        })
    }

    /// `file:line:col` of a node.
    pub(crate) fn at<T>(&self, node: &Located<T>) -> String {
        format!("{}:{}:{}", self.file, node.line, node.column)
    }

    /// An `options` node as JSON text (`null` when absent) and its `file:line:col` (the
    /// owner's position when absent), as plugins and executor factories receive them.
    pub(crate) fn options_of<T>(
        &self,
        options: Option<&Located<serde_json::Value>>,
        owner: &Located<T>,
    ) -> (String, String) {
        match options {
            Some(o) => (o.value.to_string(), self.at(o)),
            None => ("null".to_owned(), self.at(owner)),
        }
    }

    /// A config error at `node`.
    pub(crate) fn error<T>(&self, node: &Located<T>, message: impl Into<String>) -> Error {
        Error::Config {
            file: self.file.clone(),
            line: node.line,
            column: node.column,
            message: message.into(),
            detail: String::new(),
        }
    }

    /// The directory for module temp configs.
    pub(crate) fn temp_cfg_path(&self) -> PathBuf {
        PathBuf::from(
            self.aimrt
                .configurator
                .as_ref()
                .map_or_else(default_temp_cfg_path, |c| c.temp_cfg_path.clone()),
        )
    }

    /// Sections this runtime does not implement yet, present in the file.
    pub(crate) fn unimplemented_sections(&self) -> Vec<&'static str> {
        let a = &self.aimrt;
        let mut out = Vec::new();
        for (name, present) in [
            ("aimrt.parameter", a.parameter.is_some()),
            ("aimrt.allocator", a.allocator.is_some()),
        ] {
            if present {
                out.push(name);
            }
        }
        out
    }
}

fn yaml_error(file: &str, e: &serde_saphyr::Error) -> Error {
    let rendered = e.to_string();
    let first = rendered.lines().next().unwrap_or_default();
    // "error: line L column C: message" → "message"
    let message = first
        .split_once(": ")
        .map_or(first, |(_, rest)| rest)
        .split_once(": ")
        .filter(|(head, _)| head.starts_with("line "))
        .map_or_else(|| first.trim_start_matches("error: "), |(_, m)| m);
    let (line, column) = e.location().map_or((0, 0), |l| (l.line(), l.column()));
    Error::Config {
        file: file.to_owned(),
        line,
        column,
        message: explain(message),
        detail: rendered.replace("<input>", file),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config, Error> {
        Config::parse("cfg.yaml", text, |_| None)
    }

    #[test]
    fn empty_file_gives_defaults() {
        let c = parse("").unwrap();
        assert!(c.aimrt.executor.is_none());
        assert_eq!(c.temp_cfg_path(), PathBuf::from("./cfg/tmp"));
    }

    #[test]
    fn reads_aimrt_sections_and_module_roots() {
        let c = parse(
            "aimrt:\n  executor:\n    executors:\n      - name: w\n        type: simple_thread\n        options: {queue_threshold: 5}\n  module:\n    pkgs:\n      - path: ./libx.so\n        enable_modules: [A]\nA:\n  key: v\n",
        )
        .unwrap();
        let e = &c.aimrt.executor.as_ref().unwrap().executors[0];
        assert_eq!(e.name.value, "w");
        assert_eq!((e.name.line, e.name.column), (4, 15));
        assert_eq!(e.options.as_ref().unwrap().value["queue_threshold"], 5);
        assert_eq!(c.roots["A"]["key"], "v");
    }

    #[test]
    fn unknown_key_is_an_error_with_suggestion_and_location() {
        let err = parse("aimrt:\n  executor:\n    executors:\n      - name: a\n        type: t\n        optons: {}\n").unwrap_err();
        let line = err.to_string();
        assert!(
            line.starts_with("cfg.yaml:6:9: unknown key 'optons'; did you mean 'options'?"),
            "{line}"
        );
        assert!(err.detail().unwrap().contains("optons"));
    }

    #[test]
    fn syntax_error_and_negative_unsigned_are_located() {
        let err = parse("aimrt:\n  executor: [\n").unwrap_err();
        assert!(err.to_string().starts_with("cfg.yaml:2:"), "{err}");
        let err = parse("aimrt:\n  guard_thread:\n    queue_threshold: -1\n").unwrap_err();
        assert!(err.to_string().starts_with("cfg.yaml:3:22:"), "{err}");
    }

    #[test]
    fn missing_required_key_is_named() {
        let err = parse("aimrt:\n  plugin:\n    plugins:\n      - name: p\n").unwrap_err();
        assert!(err.to_string().contains("missing field `path`"), "{err}");
    }

    #[test]
    fn unset_env_var_is_an_error() {
        let err =
            parse("aimrt:\n  module:\n    pkgs:\n      - path: ${LIB_DIR}/x.so\n").unwrap_err();
        assert!(
            err.to_string()
                .starts_with("cfg.yaml:4:15: environment variable 'LIB_DIR' is not set"),
            "{err}"
        );
        let ok =
            parse("aimrt:\n  module:\n    pkgs:\n      - path: ${LIB_DIR:-./lib}/x.so\n").unwrap();
        assert_eq!(ok.aimrt.module.unwrap().pkgs[0].path.value, "./lib/x.so");
    }

    #[test]
    fn aimrt_corpus_configs_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/aimrt-configs");
        let Ok(entries) = std::fs::read_dir(&dir) else {
            panic!("the AimRT config corpus is expected at {}", dir.display());
        };
        let mut n = 0;
        for entry in entries {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "yaml") {
                let text = std::fs::read_to_string(&path).unwrap();
                let config =
                    Config::parse(&path.display().to_string(), &text, |_| Some("/opt".into()))
                        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                // The log section is fully validated too (levels, backends, their options).
                let log = crate::log::settings::LogSettings::from_config(&config)
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
                // No key is accepted-but-ignored in AimRT's own configs; the only warnings
                // left are the sections not implemented yet, which `aimrt_main` names.
                assert!(
                    log.warnings.is_empty(),
                    "{}: {:?}",
                    path.display(),
                    log.warnings
                );
                n += 1;
            }
        }
        assert!(n >= 10, "only {n} corpus files found");
    }
}
