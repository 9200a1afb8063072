//! The filters plugins register by name, for channels (ABI 1.7) and RPC (ABI 1.9): one
//! registry per kind, two sides each, beside the runtime's built-in filters.

use std::collections::BTreeMap;
use std::sync::Arc;

use aimrt_plugin_api::channel::FilterSide;
use aimrt_plugin_api::rpc::CallFilterSide;
use aimrt_plugin_api::RateLimit;

/// A side of a filter kind: its index, its name, the kind and its built-in filters.
pub(crate) trait Side: Copy {
    /// `channel` or `rpc`.
    const KIND: &'static str;
    /// The built-in filters `enable_filters` may name.
    const BUILT_IN: &'static [&'static str];
    /// 0 or 1.
    fn index(self) -> usize;
    /// The side's name in messages.
    fn side_name(self) -> &'static str;
}

impl Side for FilterSide {
    const KIND: &'static str = "channel";
    const BUILT_IN: &'static [&'static str] = &["debug_log"];
    fn index(self) -> usize {
        self.code() as usize
    }
    fn side_name(self) -> &'static str {
        self.name()
    }
}

impl Side for CallFilterSide {
    const KIND: &'static str = "rpc";
    const BUILT_IN: &'static [&'static str] = &["debug_log", "time_cost"];
    fn index(self) -> usize {
        self.code() as usize
    }
    fn side_name(self) -> &'static str {
        self.name()
    }
}

/// A filter a plugin registered.
pub(crate) struct PluginFilter<R> {
    pub(crate) name: String,
    pub(crate) owner: String,
    pub(crate) raw: R,
    /// Failures of the filter after it passed its subject on (reported, not counted).
    pub(crate) late: RateLimit,
}

/// The filters plugins registered, by side and name.
pub(crate) struct Registered<S, R> {
    by_side: [BTreeMap<String, Arc<PluginFilter<R>>>; 2],
    side: std::marker::PhantomData<S>,
}

impl<S, R> Default for Registered<S, R> {
    fn default() -> Self {
        Registered {
            by_side: [BTreeMap::new(), BTreeMap::new()],
            side: std::marker::PhantomData,
        }
    }
}

impl<S: Side, R> Registered<S, R> {
    /// Records `raw` under `name` for `side`; a name taken (or built in) is refused.
    pub(crate) fn register(
        &mut self,
        name: &str,
        side: S,
        raw: R,
        owner: &str,
    ) -> Result<(), String> {
        let (kind, side_name) = (S::KIND, side.side_name());
        if name.is_empty() {
            return Err(format!("a {kind} {side_name} filter needs a name"));
        }
        if S::BUILT_IN.contains(&name) {
            return Err(format!(
                "{kind} {side_name} filter '{name}' is built into the runtime; give the filter another name"
            ));
        }
        let map = &mut self.by_side[side.index()];
        if let Some(first) = map.get(name) {
            return Err(format!(
                "{kind} {side_name} filter '{name}' is already registered by '{}'",
                first.owner
            ));
        }
        map.insert(
            name.to_owned(),
            Arc::new(PluginFilter {
                name: name.to_owned(),
                owner: owner.to_owned(),
                raw,
                late: RateLimit::from_millis(1000),
            }),
        );
        tracing::debug!(target: "aimrt", "plugin '{owner}' registered {kind} {side_name} filter '{name}'");
        Ok(())
    }

    /// Every name `enable_filters` may list for `side`: the built-in ones, then the
    /// registered ones in name order.
    pub(crate) fn names(&self, side: S) -> Vec<&str> {
        S::BUILT_IN
            .iter()
            .copied()
            .chain(self.by_side[side.index()].keys().map(String::as_str))
            .collect()
    }

    /// The filter registered under `name` for `side`.
    pub(crate) fn get(&self, side: S, name: &str) -> Option<&Arc<PluginFilter<R>>> {
        self.by_side[side.index()].get(name)
    }

    /// The stages of a chain of `listed` (names checked against [`names`](Self::names)
    /// already), in the order they run: the last listed first. `built_in` makes the stage
    /// of a built-in name, `plugin` that of a registered filter.
    pub(crate) fn stages<T>(
        &self,
        side: S,
        listed: &[String],
        built_in: impl Fn(&str) -> Option<T>,
        plugin: impl Fn(Arc<PluginFilter<R>>) -> T,
    ) -> Vec<T> {
        (listed.iter().rev())
            .filter_map(|name| {
                built_in(name).or_else(|| self.get(side, name).map(|f| plugin(f.clone())))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_per_kind_and_side_and_refused_when_taken_or_built_in() {
        let mut rpc: Registered<CallFilterSide, u8> = Registered::default();
        rpc.register("trace", CallFilterSide::Client, 1, "p")
            .unwrap();
        rpc.register("trace", CallFilterSide::Server, 2, "p")
            .unwrap();
        let err = rpc
            .register("trace", CallFilterSide::Client, 3, "q")
            .unwrap_err();
        assert_eq!(
            err,
            "rpc client filter 'trace' is already registered by 'p'"
        );
        let err = rpc
            .register("time_cost", CallFilterSide::Server, 4, "q")
            .unwrap_err();
        assert!(err.contains("built into the runtime"), "{err}");
        assert_eq!(
            rpc.names(CallFilterSide::Client),
            ["debug_log", "time_cost", "trace"]
        );
        assert_eq!(
            rpc.get(CallFilterSide::Server, "trace").map(|f| f.raw),
            Some(2)
        );

        let mut channel: Registered<FilterSide, u8> = Registered::default();
        let err = channel
            .register("", FilterSide::Publish, 1, "p")
            .unwrap_err();
        assert_eq!(err, "a channel publish filter needs a name");
        // `time_cost` is built in for RPC only.
        channel
            .register("time_cost", FilterSide::Subscribe, 1, "p")
            .unwrap();
        assert_eq!(channel.names(FilterSide::Publish), ["debug_log"]);
    }
}
