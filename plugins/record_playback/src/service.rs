//! The control service, `aimrt.protocols.record_playback_plugin.RecordPlaybackService`
//! (AimRT's `record_playback.proto`), in `pb` and `json`. Each answer says what happened:
//! `common_rsp.code` is 0 when the call did what it asked, else AimRT's code with a
//! message that begins with AimRT's code name (`INVALID_ACTION_NAME: …`) and says why.

use std::collections::BTreeMap;
use std::sync::Arc;

use aimrt_plugin_api::rpc::serve_message as serve;
use aimrt_plugin_api::{Error, Registrar, ServiceError};
use aimrt_protocols::record_playback_plugin as pb;

use crate::playback::Player;
use crate::record::{code, Recorder, Refusal};

/// The actions, by name.
#[derive(Default)]
pub(crate) struct Actions {
    pub(crate) records: BTreeMap<String, Arc<Recorder>>,
    pub(crate) players: BTreeMap<String, Arc<Player>>,
}

/// The default service name.
pub(crate) const SERVICE: &str = "aimrt.protocols.record_playback_plugin.RecordPlaybackService";

fn code_name(code: u32) -> &'static str {
    match code {
        code::INVALID_ACTION_NAME => "INVALID_ACTION_NAME",
        code::INVALID_ACTION_MODE => "INVALID_ACTION_MODE",
        code::START_RECORD_FAILED => "START_RECORD_FAILED",
        code::START_PLAYBACK_FAILED => "START_PLAYBACK_FAILED",
        code::STOP_RECORD_FAILED => "STOP_RECORD_FAILED",
        code::INVALID_TOPIC_META => "INVALID_TOPIC_META",
        _ => "FAILED",
    }
}

fn common(result: Result<(), Refusal>) -> pb::CommonRsp {
    match result {
        Ok(()) => pb::CommonRsp::default(),
        Err((code, why)) => {
            tracing::warn!("record_playback_plugin: {why}");
            pb::CommonRsp {
                code,
                msg: format!("{}: {why}", code_name(code)),
            }
        }
    }
}

impl Actions {
    fn record(&self, name: &str) -> Result<&Arc<Recorder>, Refusal> {
        self.records.get(name).ok_or_else(|| {
            (
                code::INVALID_ACTION_NAME,
                format!(
                    "no record action is named '{name}'; the record actions: {}",
                    list(self.records.keys())
                ),
            )
        })
    }

    fn player(&self, name: &str) -> Result<&Arc<Player>, Refusal> {
        self.players.get(name).ok_or_else(|| {
            (
                code::INVALID_ACTION_NAME,
                format!(
                    "no playback action is named '{name}'; the playback actions: {}",
                    list(self.players.keys())
                ),
            )
        })
    }

    fn start_record(&self, r: pb::StartRecordReq) -> pb::StartRecordRsp {
        let mut filefolder = String::new();
        let result = self.record(&r.action_name).and_then(|a| {
            filefolder = a.start_record(
                u64::from(r.preparation_duration_s),
                u64::from(r.record_duration_s),
            )?;
            Ok(())
        });
        pb::StartRecordRsp {
            common_rsp: Some(common(result)),
            filefolder,
        }
    }

    fn start_playback(&self, r: pb::StartPlaybackReq) -> pb::CommonRsp {
        common(self.player(&r.action_name).and_then(|p| {
            if !p.signal {
                return Err((
                    code::INVALID_ACTION_MODE,
                    format!("playback action '{}' is imd: it plays at start; StartPlayback and StopPlayback control signal actions", p.name),
                ));
            }
            p.play(u64::from(r.skip_duration_s), u64::from(r.play_duration_s))
                .map_err(|e| (code::START_PLAYBACK_FAILED, format!("playback action '{}': {e}", p.name)))
        }))
    }

    fn stop_playback(&self, r: pb::StopPlaybackReq) -> pb::CommonRsp {
        common(self.player(&r.action_name).and_then(|p| {
            if p.stop() {
                Ok(())
            } else {
                // AimRT has no code for it; 4 is the playback's failure code.
                Err((
                    code::START_PLAYBACK_FAILED,
                    format!("playback action '{}' is not playing", p.name),
                ))
            }
        }))
    }

    fn update_record_action(&self, r: pb::UpdateRecordActionReq) -> pb::UpdateRecordActionRsp {
        let topics: Vec<_> = r
            .topic_metas
            .into_iter()
            .map(|t| (t.topic_name, t.msg_type, t.record_enabled, t.sample_freq))
            .collect();
        pb::UpdateRecordActionRsp {
            common_rsp: Some(common(
                self.record(&r.action_name)
                    .and_then(|a| a.update(r.record_enabled, &topics)),
            )),
        }
    }

    fn status(&self, r: pb::GetRecordActionStatusReq) -> pb::GetRecordActionStatusRsp {
        let names: Vec<String> = if r.action_names.is_empty() {
            self.records.keys().cloned().collect()
        } else {
            r.action_names
        };
        let mut list = Vec::new();
        for name in &names {
            match self.record(name) {
                Ok(a) => list.push(pb::RecordActionStatus {
                    action_name: name.clone(),
                    record_enabled: a.enabled(),
                    topic_meta_list: a
                        .topic_status()
                        .into_iter()
                        .map(
                            |(topic_name, msg_type, record_enabled, freq)| pb::TopicMeta {
                                topic_name,
                                msg_type,
                                record_enabled,
                                sample_freq: Some(freq),
                            },
                        )
                        .collect(),
                }),
                Err(refusal) => {
                    return pb::GetRecordActionStatusRsp {
                        common_rsp: Some(common(Err(refusal))),
                        record_action_status_list: Vec::new(),
                    }
                }
            }
        }
        pb::GetRecordActionStatusRsp {
            common_rsp: Some(common(Ok(()))),
            record_action_status_list: list,
        }
    }
}

fn list<'a>(names: impl Iterator<Item = &'a String>) -> String {
    let v: Vec<&str> = names.map(String::as_str).collect();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// Registers the seven methods as `pb:/<service>/<Method>`.
pub(crate) fn register(
    registrar: &mut Registrar<'_>,
    service: &str,
    actions: &Arc<Actions>,
) -> Result<(), Error> {
    type Handler = fn(&Actions, &str, &[u8]) -> Result<Vec<u8>, ServiceError>;
    let methods: [(&str, Handler); 7] = [
        ("StartRecord", |a, f, b| serve(f, b, |r| a.start_record(r))),
        ("StopRecord", |a, f, b| {
            serve(f, b, |r: pb::StopRecordReq| {
                common(a.record(&r.action_name).and_then(|x| x.stop_record()))
            })
        }),
        ("StartPlayback", |a, f, b| {
            serve(f, b, |r| a.start_playback(r))
        }),
        ("StopPlayback", |a, f, b| {
            serve(f, b, |r| a.stop_playback(r))
        }),
        ("UpdateMetadata", |a, f, b| {
            serve(f, b, |r: pb::UpdateMetadataReq| {
                common(
                    a.record(&r.action_name)
                        .map(|x| x.update_metadata(&r.kv_pairs)),
                )
            })
        }),
        ("UpdateRecordAction", |a, f, b| {
            serve(f, b, |r| a.update_record_action(r))
        }),
        ("GetRecordActionStatus", |a, f, b| {
            serve(f, b, |r| a.status(r))
        }),
    ];
    for (method, handler) in methods {
        let actions = actions.clone();
        registrar.register_service(&format!("pb:/{service}/{method}"), move |format, bytes| {
            handler(&actions, format, bytes)
        })?;
    }
    Ok(())
}
