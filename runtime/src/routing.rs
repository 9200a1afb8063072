//! Name-routing rules, shared by `aimrt.rpc` (`func_name`) and `aimrt.channel`
//! (`topic_name`): a regex that must match the **whole** name, the backends it enables, and
//! filters (the built-in ones of each section). The first rule that matches a name decides.

use regex::Regex;

use crate::config::{BackendEntry, Config, Located, RpcFuncOptions, TopicOptions};
use crate::Error;
use aimrt_plugin_api::__private::did_you_mean;

/// One rule as the config writes it.
pub(crate) struct RuleEntry<'a> {
    /// The regex (`func_name` / `topic_name`).
    pub(crate) name: &'a Located<String>,
    /// `enable_backends`.
    pub(crate) enable_backends: &'a [Located<String>],
    /// `enable_filters`.
    pub(crate) enable_filters: &'a [Located<String>],
}

/// A config node that is a rule (`servers_options[i]`, `pub_topics_options[i]`, …).
pub(crate) trait RuleSource {
    /// The regex key, for messages (`func_name`, `topic_name`).
    const KEY: &'static str;
    /// What the rule routes, for messages (`call`, `message`).
    const ITEM: &'static str;
    /// Its parts.
    fn rule(&self) -> RuleEntry<'_>;
}

impl RuleSource for RpcFuncOptions {
    const KEY: &'static str = "func_name";
    const ITEM: &'static str = "call";
    fn rule(&self) -> RuleEntry<'_> {
        RuleEntry {
            name: &self.func_name,
            enable_backends: &self.enable_backends,
            enable_filters: &self.enable_filters,
        }
    }
}

impl RuleSource for TopicOptions {
    const KEY: &'static str = "topic_name";
    const ITEM: &'static str = "message";
    fn rule(&self) -> RuleEntry<'_> {
        RuleEntry {
            name: &self.topic_name,
            enable_backends: &self.enable_backends,
            enable_filters: &self.enable_filters,
        }
    }
}

/// The backend types of a `backends` list, each listed once (`section`: `aimrt.rpc`, …).
pub(crate) fn listed_backends<'a>(
    config: &Config,
    backends: &'a [BackendEntry],
    section: &str,
) -> Result<Vec<&'a str>, Error> {
    if let Some(again) = Located::repeated(backends.iter().map(|b| &b.type_name)) {
        return Err(config.error(
            again,
            format!(
                "backend '{}' is listed twice in {section}.backends; list each backend once",
                again.value
            ),
        ));
    }
    Ok(backends
        .iter()
        .map(|b| b.type_name.value.as_str())
        .collect())
}

#[derive(Clone)]
struct Rule {
    pattern: Regex,
    backends: Vec<String>,
    filters: Vec<String>,
}

/// Compiled rules, in config order.
#[derive(Default, Clone)]
pub(crate) struct Rules(Vec<Rule>);

impl Rules {
    /// Compiles `sources`; each `enable_backends` entry must be one of `listed`, each
    /// `enable_filters` entry one of `filters`.
    pub(crate) fn compile<S: RuleSource>(
        config: &Config,
        sources: &[S],
        listed: &[&str],
        filters: &[&str],
        section: &str,
    ) -> Result<Rules, Error> {
        let key = S::KEY;
        let mut rules = Vec::new();
        for e in sources.iter().map(RuleSource::rule) {
            let pattern = &e.name.value;
            let compiled = aimrt_plugin_api::whole_match(pattern).map_err(|err| {
                config.error(
                    e.name,
                    format!("{key} '{pattern}' is not a valid regular expression: {err}"),
                )
            })?;
            let lists = if listed.is_empty() {
                "none".to_owned()
            } else {
                listed.join(", ")
            };
            check_known(config, e.enable_backends, listed, |name, hint| {
                format!("enable_backends names '{name}', which {section}.backends does not list{hint} (it lists: {lists})")
            })?;
            check_known(config, e.enable_filters, filters, |name, hint| {
                format!(
                    "enable_filters names '{name}', which is not a filter{hint}; the filters are: {}",
                    filters.join(", ")
                )
            })?;
            if let Some(again) = Located::repeated(e.enable_backends.iter()) {
                return Err(config.error(again, format!(
                    "enable_backends lists '{}' twice, which would hand each {} to it twice; list each backend once",
                    again.value, S::ITEM
                )));
            }
            if let Some(again) = Located::repeated(e.enable_filters.iter()) {
                return Err(config.error(again, format!(
                    "enable_filters lists '{}' twice, which would run it twice around each {}; list each filter once",
                    again.value, S::ITEM
                )));
            }
            rules.push(Rule {
                pattern: compiled,
                backends: e.enable_backends.iter().map(|b| b.value.clone()).collect(),
                filters: e.enable_filters.iter().map(|f| f.value.clone()).collect(),
            });
        }
        Ok(Rules(rules))
    }

    /// The backends of the first rule matching the whole of `name` (`None`: no rule
    /// matches).
    pub(crate) fn backends_for(&self, name: &str) -> Option<&[String]> {
        self.0
            .iter()
            .find(|r| r.pattern.is_match(name))
            .map(|r| r.backends.as_slice())
    }

    /// The filters of the first rule matching the whole of `name`, in config order.
    pub(crate) fn filters_for(&self, name: &str) -> &[String] {
        self.0
            .iter()
            .find(|r| r.pattern.is_match(name))
            .map_or(&[], |r| r.filters.as_slice())
    }

    /// Whether the first rule matching `name` enables `backend`.
    pub(crate) fn enables(&self, name: &str, backend: &str) -> bool {
        self.backends_for(name)
            .is_some_and(|b| b.iter().any(|x| x == backend))
    }
}

/// An error at the first of `names` that is not one of `known`: `say(name, hint)`, the
/// hint a "did you mean" or empty.
fn check_known(
    config: &Config,
    names: &[Located<String>],
    known: &[&str],
    say: impl Fn(&str, String) -> String,
) -> Result<(), Error> {
    match names.iter().find(|n| !known.contains(&n.value.as_str())) {
        Some(n) => Err(config.error(
            n,
            say(&n.value, did_you_mean(&n.value, known.iter().copied())),
        )),
        None => Ok(()),
    }
}

#[cfg(test)]
impl Rules {
    /// Rules from `(regex, backends)` pairs.
    pub(crate) fn test(list: &[(&str, &[&str])]) -> Rules {
        Rules(
            list.iter()
                .map(|(re, backends)| Rule {
                    pattern: aimrt_plugin_api::whole_match(re).unwrap(),
                    backends: backends.iter().map(|b| (*b).to_owned()).collect(),
                    filters: Vec::new(),
                })
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rules(list: &[(&str, &[&str])]) -> Rules {
        Rules::test(list)
    }

    #[test]
    fn the_first_rule_matching_the_whole_name_decides() {
        let r = rules(&[
            ("pb:/svc/Pause", &[]),
            ("pb:/svc/.*", &["http"]),
            (".*", &["local"]),
        ]);
        assert!(!r.enables("pb:/svc/Pause", "http"));
        assert!(r.enables("pb:/svc/SetTimeRatio", "http"));
        assert!(!r.enables("pb:/svc/SetTimeRatio", "local"));
        // Full match: `pb:/svc/Pause` does not match inside a longer name.
        assert!(r.enables("xpb:/svc/Pause", "local"));
        assert!(!r.enables("xpb:/svc/Pause", "http"));
        assert_eq!(rules(&[("a", &["x"])]).backends_for("b"), None);
    }

    /// A backend the section does not list, or a filter that is not one, is an error at
    /// its place naming the right ones.
    #[test]
    fn unknown_backends_and_filters_are_errors_at_their_place() {
        let compile = |rule: &str| {
            let text = format!("aimrt:\n  channel:\n    pub_topics_options:\n      - {rule}\n");
            let config = Config::parse("cfg.yaml", &text, |_| None).unwrap();
            let section = config.aimrt.channel.as_ref().unwrap();
            Rules::compile(
                &config,
                &section.pub_topics_options,
                &["local", "zenoh"],
                &["debug_log"],
                "aimrt.channel",
            )
            .map(|_| ())
            .map_err(|e| e.to_string())
        };
        for (rule, expected) in [
            ("{topic_name: a, enable_backends: [local], enable_filters: [debug_log]}", ""),
            (
                "{topic_name: a, enable_backends: [local, zenho]}",
                "cfg.yaml:4:50: enable_backends names 'zenho', which aimrt.channel.backends does not list; did you mean 'zenoh'? (it lists: local, zenoh)",
            ),
            (
                "{topic_name: a, enable_backends: [local], enable_filters: [time_cost]}",
                "cfg.yaml:4:68: enable_filters names 'time_cost', which is not a filter; the filters are: debug_log",
            ),
            (
                "{topic_name: a, enable_backends: [local, zenoh, local]}",
                "cfg.yaml:4:57: enable_backends lists 'local' twice, which would hand each message to it twice; list each backend once",
            ),
            (
                "{topic_name: a, enable_backends: [local], enable_filters: [debug_log, debug_log]}",
                "cfg.yaml:4:79: enable_filters lists 'debug_log' twice, which would run it twice around each message; list each filter once",
            ),
        ] {
            assert_eq!(compile(rule).err().unwrap_or_default(), expected, "{rule}");
        }
        // A chain as long as a config can list is refused at once, not run until the
        // stack overflows (10 000 `debug_log`s did, in a debug build).
        let long = vec!["debug_log"; 100_000].join(", ");
        let err = compile(&format!(
            "{{topic_name: a, enable_backends: [local], enable_filters: [{long}]}}"
        ))
        .unwrap_err();
        assert!(err.contains("lists 'debug_log' twice"), "{err}");
    }
}
