//! The runtime's errors. Each displays as one line naming the file, the cause and the fix.

use std::path::PathBuf;

/// Why the runtime could not start or run.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The config file could not be read.
    #[error("cannot read config file '{path}': {source}; check --cfg_file_path")]
    ConfigRead {
        /// The path given.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The config is invalid. `detail` carries a multi-line snippet for stderr.
    #[error("{}: {message}", at(file, *line, *column))]
    Config {
        /// The config file.
        file: String,
        /// 1-based line (0 if unknown).
        line: u64,
        /// 1-based column (0 if unknown).
        column: u64,
        /// What is wrong and what would be right.
        message: String,
        /// The message with a snippet of the file, for humans.
        detail: String,
    },
    /// A plugin or pkg library could not be used.
    #[error("{what} ({path}): {message}")]
    Library {
        /// `plugin 'x'` or `pkg`.
        what: String,
        /// The library path.
        path: String,
        /// What is wrong and how to fix it.
        message: String,
    },
    /// A plugin failed.
    #[error("plugin '{plugin}' failed to {action}: {message}")]
    Plugin {
        /// The plugin's name.
        plugin: String,
        /// `initialize` or `start`.
        action: &'static str,
        /// Its message.
        message: String,
    },
    /// An executor could not be built.
    #[error("executor '{executor}' ({location}): {message}")]
    Executor {
        /// The executor's name.
        executor: String,
        /// Where it is declared, `file:line:col`.
        location: String,
        /// What is wrong.
        message: String,
    },
    /// An RPC backend failed to start.
    #[error("rpc backend '{backend}' failed to start: {message}")]
    Rpc {
        /// The backend type.
        backend: String,
        /// Its message.
        message: String,
    },
    /// A channel backend failed to start.
    #[error("channel backend '{backend}' failed to start: {message}")]
    Channel {
        /// The backend type.
        backend: String,
        /// Its message.
        message: String,
    },
    /// A module failed.
    #[error("module '{module}' ({pkg}) failed to {action}: {message}")]
    Module {
        /// The module's name.
        module: String,
        /// Its pkg library, or `registered in code`.
        pkg: String,
        /// `register`, `initialize` or `start`.
        action: &'static str,
        /// Its message.
        message: String,
    },
    /// A file the runtime writes could not be written.
    #[error("cannot write '{path}': {source}")]
    Write {
        /// The path.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A command-line error.
    #[error("{0}")]
    Cli(String),
    /// A dump file could not be written.
    #[error("cannot write '{}' (--{flag}): {source}; give a path in a folder that exists and can be written", path.display())]
    Dump {
        /// The file.
        path: std::path::PathBuf,
        /// The flag that named it, without `--`.
        flag: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The config could not be written as YAML for `--dump_cfg_file`.
    #[error("cannot write the config as YAML to '{}' (--dump_cfg_file): {reason}", path.display())]
    DumpFormat {
        /// The file.
        path: std::path::PathBuf,
        /// What the YAML writer said.
        reason: String,
    },
    /// A log backend could not be set up.
    #[error("{location}: {message}")]
    Log {
        /// Where the backend is declared, `file:line:col`.
        location: String,
        /// What is wrong and what would be right.
        message: String,
    },
    /// A runtime thread could not be created or configured as asked.
    #[error(transparent)]
    Thread(aimrt_plugin_api::Error),
}

/// `file:line:col`, or just `file` for an error about the whole file (line 0).
fn at(file: &str, line: u64, column: u64) -> String {
    if line == 0 {
        file.to_owned()
    } else {
        format!("{file}:{line}:{column}")
    }
}

impl Error {
    /// A multi-line explanation (with a config snippet where there is one).
    pub fn detail(&self) -> Option<&str> {
        match self {
            Error::Config { detail, .. } if !detail.is_empty() => Some(detail),
            _ => None,
        }
    }
}
