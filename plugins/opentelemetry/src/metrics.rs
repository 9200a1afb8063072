//! AimRT's `otp_metrics`: counters of messages and calls and their sizes, histograms of
//! call times, kept per label set from the plugin's start (cumulative) and sent to the
//! collector every `metrics_export_interval_ms`, and once more at shutdown.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Duration;

use crate::lock;
use aimrt_plugin_api::RateLimit;
use prost::Message;

use crate::exporter::{post_blocking, runtime, Endpoint};
use crate::otlp::{
    ExportMetricsServiceRequest, Histogram, HistogramDataPoint, InstrumentationScope, KeyValue,
    Metric, MetricData, NumberDataPoint, Resource, ResourceMetrics, ScopeMetrics, Sum, CUMULATIVE,
};
use crate::trace::now_ns;

/// The buckets' upper bounds of the call-time histograms, in µs, when
/// `rpc_time_cost_histogram_boundaries` does not give them (OpenTelemetry's default
/// histogram bounds, which AimRT's SDK uses).
pub(crate) const BOUNDS: [f64; 15] = [
    0.0, 5.0, 10.0, 25.0, 50.0, 75.0, 100.0, 250.0, 500.0, 750.0, 1000.0, 2500.0, 5000.0, 7500.0,
    10000.0,
];

/// A metric AimRT's plugin defines: its name, description and unit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) struct Def {
    pub(crate) name: &'static str,
    pub(crate) description: &'static str,
    pub(crate) unit: &'static str,
}

macro_rules! defs {
    ($($id:ident = $name:literal, $description:literal, $unit:literal;)*) => {
        $(pub(crate) const $id: Def = Def { name: $name, description: $description, unit: $unit };)*
    };
}

defs! {
    CHN_PUB_NUM = "chn.pub.msg_num", "Total num of channel publish msg", "";
    CHN_SUB_NUM = "chn.sub.msg_num", "Total num of channel subscribe msg", "";
    CHN_PUB_SIZE = "chn.pub.msg_size", "Total size of channel publish msg", "bytes";
    CHN_SUB_SIZE = "chn.sub.msg_size", "Total size of channel subscribe msg", "bytes";
    RPC_CLI_NUM = "rpc.client.invoke_num", "Total num of rpc client invoke", "";
    RPC_SVR_NUM = "rpc.server.invoke_num", "Total num of rpc server invoke", "";
    RPC_CLI_REQ_SIZE = "rpc.client.req_size", "Total size of rpc client request", "bytes";
    RPC_CLI_RSP_SIZE = "rpc.client.rsp_size", "Total size of rpc client response", "bytes";
    RPC_SVR_REQ_SIZE = "rpc.server.req_size", "Total size of rpc server request", "bytes";
    RPC_SVR_RSP_SIZE = "rpc.server.rsp_size", "Total size of rpc server response", "bytes";
    RPC_CLI_TIME = "rpc.client.time_cost", "Time cost of rpc client", "us";
    RPC_SVR_TIME = "rpc.server.time_cost", "Time cost of rpc server", "us";
}

/// Labels, in a fixed order.
pub(crate) type Labels = Vec<(&'static str, String)>;

#[derive(Debug, Clone)]
struct Hist {
    count: u64,
    sum: f64,
    /// One more than the bounds.
    buckets: Vec<u64>,
    min: f64,
    max: f64,
}

impl Hist {
    fn new(bounds: usize) -> Hist {
        Hist {
            count: 0,
            sum: 0.0,
            buckets: vec![0; bounds + 1],
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
        }
    }

    fn record(&mut self, bounds: &[f64], v: f64) {
        self.count += 1;
        self.sum += v;
        self.min = self.min.min(v);
        self.max = self.max.max(v);
        let i = bounds.iter().position(|b| v <= *b).unwrap_or(bounds.len());
        self.buckets[i] += 1;
    }
}

/// The values, by metric and label set.
pub(crate) struct Meter {
    /// The histograms' bucket bounds, strictly increasing.
    bounds: Vec<f64>,
    sums: Mutex<BTreeMap<(Def, Labels), u64>>,
    hists: Mutex<BTreeMap<(Def, Labels), Hist>>,
}

impl Meter {
    /// A meter whose histograms have buckets up to each of `bounds`, and one beyond;
    /// `Err` when they are not strictly increasing finite numbers.
    pub(crate) fn new(bounds: Vec<f64>) -> Result<Meter, String> {
        if bounds.iter().any(|b| !b.is_finite()) || bounds.windows(2).any(|w| w[0] >= w[1]) {
            return Err(format!(
                "{bounds:?} must be finite numbers in strictly increasing order"
            ));
        }
        Ok(Meter {
            bounds,
            sums: Mutex::default(),
            hists: Mutex::default(),
        })
    }

    /// Adds `v` to a counter.
    pub(crate) fn add(&self, def: Def, labels: Labels, v: u64) {
        *lock(&self.sums).entry((def, labels)).or_default() += v;
    }

    /// Records `v` in a histogram.
    pub(crate) fn record(&self, def: Def, labels: Labels, v: f64) {
        let bounds = &self.bounds;
        lock(&self.hists)
            .entry((def, labels))
            .or_insert_with(|| Hist::new(bounds.len()))
            .record(bounds, v);
    }

    /// Every metric's values now, as OTLP metrics counting from `start`.
    pub(crate) fn snapshot(&self, start: u64) -> Vec<Metric> {
        let now = now_ns();
        let attributes = |labels: &Labels| -> Vec<KeyValue> {
            labels.iter().map(|(k, v)| KeyValue::text(k, v)).collect()
        };
        let mut out: BTreeMap<Def, MetricData> = BTreeMap::new();
        for ((def, labels), v) in lock(&self.sums).iter() {
            let entry = out.entry(*def).or_insert_with(|| {
                MetricData::Sum(Sum {
                    data_points: Vec::new(),
                    aggregation_temporality: CUMULATIVE,
                    is_monotonic: true,
                })
            });
            if let MetricData::Sum(sum) = entry {
                sum.data_points.push(NumberDataPoint {
                    attributes: attributes(labels),
                    start_time_unix_nano: start,
                    time_unix_nano: now,
                    as_int: i64::try_from(*v).unwrap_or(i64::MAX),
                });
            }
        }
        for ((def, labels), h) in lock(&self.hists).iter() {
            let entry = out.entry(*def).or_insert_with(|| {
                MetricData::Histogram(Histogram {
                    data_points: Vec::new(),
                    aggregation_temporality: CUMULATIVE,
                })
            });
            if let MetricData::Histogram(hist) = entry {
                hist.data_points.push(HistogramDataPoint {
                    attributes: attributes(labels),
                    start_time_unix_nano: start,
                    time_unix_nano: now,
                    count: h.count,
                    sum: Some(h.sum),
                    bucket_counts: h.buckets.clone(),
                    explicit_bounds: self.bounds.clone(),
                    min: (h.count > 0).then_some(h.min),
                    max: (h.count > 0).then_some(h.max),
                });
            }
        }
        out.into_iter()
            .map(|(def, data)| Metric {
                name: def.name.to_owned(),
                description: def.description.to_owned(),
                unit: def.unit.to_owned(),
                data: Some(data),
            })
            .collect()
    }
}

/// Sends the meter's values every interval, and once more when closed.
pub(crate) struct MetricsExporter {
    stop: Mutex<Option<mpsc::Sender<()>>>,
    ended: Mutex<Option<mpsc::Receiver<()>>>,
    sent: Arc<AtomicU64>,
    failed: Arc<AtomicU64>,
}

impl MetricsExporter {
    pub(crate) fn start(
        meter: Arc<Meter>,
        endpoint: Endpoint,
        resource: Vec<KeyValue>,
        scope: String,
        interval: Duration,
        timeout: Duration,
    ) -> Result<MetricsExporter, String> {
        let (stop_tx, stop_rx) = mpsc::channel::<()>();
        let (done_tx, done_rx) = mpsc::channel();
        let sent = Arc::new(AtomicU64::new(0));
        let failed = Arc::new(AtomicU64::new(0));
        let (ok, bad) = (sent.clone(), failed.clone());
        let start = now_ns();
        std::thread::Builder::new()
            .name("aimrt_otlp_metrics".into())
            .spawn(move || {
                let Some(rt) = runtime() else {
                    tracing::error!(target: "aimrt", "opentelemetry_plugin: cannot start the metrics exporter's runtime: no metric is sent");
                    return;
                };
                let alarm = RateLimit::from_millis(10_000);
                loop {
                    let last = !matches!(
                        stop_rx.recv_timeout(interval),
                        Err(mpsc::RecvTimeoutError::Timeout)
                    );
                    let request = ExportMetricsServiceRequest {
                        resource_metrics: vec![ResourceMetrics {
                            resource: Some(Resource {
                                attributes: resource.clone(),
                            }),
                            scope_metrics: vec![ScopeMetrics {
                                scope: Some(InstrumentationScope {
                                    name: scope.clone(),
                                    version: String::new(),
                                }),
                                metrics: meter.snapshot(start),
                            }],
                        }],
                    };
                    match post_blocking(&rt, &endpoint, request.encode_to_vec(), timeout) {
                        Ok(()) => {
                            ok.fetch_add(1, Ordering::Relaxed);
                        }
                        Err(why) => {
                            bad.fetch_add(1, Ordering::Relaxed);
                            if let Some(held) = alarm.admit() {
                                tracing::warn!(target: "aimrt", "opentelemetry_plugin: metrics not exported to {endpoint}: {why} ({held} more failed exports since the last such line)");
                            }
                        }
                    }
                    if last {
                        break;
                    }
                }
                let _ = done_tx.send(());
            })
            .map_err(|e| format!("cannot start the metrics exporter's thread: {e}"))?;
        Ok(MetricsExporter {
            stop: Mutex::new(Some(stop_tx)),
            ended: Mutex::new(Some(done_rx)),
            sent,
            failed,
        })
    }

    /// Sends the values once more (given the export timeout and a second) and stops.
    pub(crate) fn close(&self, timeout: Duration) {
        drop(lock(&self.stop).take());
        if let Some(ended) = lock(&self.ended).take() {
            if ended
                .recv_timeout(timeout + Duration::from_secs(1))
                .is_err()
            {
                tracing::warn!(target: "aimrt", "opentelemetry_plugin: the last metrics export did not finish in time");
            }
        }
        tracing::info!(target: "aimrt", "opentelemetry_plugin: {} metrics exports sent, {} failed",
            self.sent.load(Ordering::Relaxed), self.failed.load(Ordering::Relaxed));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_histogram_counts_each_value_in_the_first_bucket_whose_bound_holds_it() {
        let meter = Meter::new(BOUNDS.to_vec()).unwrap();
        let labels = || vec![("func_name", "f".to_owned())];
        for v in [0.0, 3.0, 5.0, 6.0, 20_000.0] {
            meter.record(RPC_CLI_TIME, labels(), v);
        }
        meter.add(RPC_CLI_NUM, labels(), 5);
        meter.add(RPC_CLI_NUM, labels(), 2);
        let metrics = meter.snapshot(1);
        let num = metrics
            .iter()
            .find(|m| m.name == "rpc.client.invoke_num")
            .unwrap();
        let Some(MetricData::Sum(sum)) = &num.data else {
            panic!("{num:?}")
        };
        assert!(sum.is_monotonic);
        assert_eq!(sum.data_points[0].as_int, 7);
        let time = metrics
            .iter()
            .find(|m| m.name == "rpc.client.time_cost")
            .unwrap();
        assert_eq!(time.unit, "us");
        let Some(MetricData::Histogram(h)) = &time.data else {
            panic!("{time:?}")
        };
        let p = &h.data_points[0];
        assert_eq!(p.count, 5);
        assert_eq!(p.bucket_counts.len(), BOUNDS.len() + 1);
        // 0 → (..0], 3 and 5 → (0, 5], 6 → (5, 10], 20 000 → (10 000, ..).
        assert_eq!(&p.bucket_counts[..3], &[1, 2, 1]);
        assert_eq!(p.bucket_counts[BOUNDS.len()], 1);
        assert_eq!(
            (p.min, p.max, p.sum),
            (Some(0.0), Some(20_000.0), Some(20_014.0))
        );
        assert_eq!(p.attributes[0].as_text(), Some("f"));
    }

    #[test]
    fn bounds_must_increase_strictly() {
        assert!(Meter::new(vec![0.0, 50.0, 150.0]).is_ok());
        assert!(Meter::new(vec![]).is_ok());
        for bad in [
            vec![0.0, 0.0],
            vec![5.0, 1.0],
            vec![f64::NAN],
            vec![0.0, f64::INFINITY],
        ] {
            assert!(Meter::new(bad.clone()).is_err(), "{bad:?}");
        }
    }
}
