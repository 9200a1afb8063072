//! The app-mode example binaries, run as a user runs them: `<binary> ./cfg.yaml` with
//! AimRT's app-mode configs (only pkg paths changed), stopped with Ctrl-C; and the hello
//! world module from its pkg under `aimrt_main`.

use std::process::Command;
use std::time::Duration;

use aimrt_e2e::{binary, example_config, Running};

const WAIT: Duration = Duration::from_secs(30);

#[test]
fn helloworld_app_runs_its_module_registered_in_code_until_ctrl_c() {
    let mut run = Running::start_program(
        &binary("helloworld_app"),
        &["./cfg.yaml"],
        &example_config("helloworld_app_mode"),
    );
    run.wait_for("cfg [key1 : val1]", WAIT);
    run.wait_for("cfg [key2 : val2]", WAIT);
    run.wait_for("[HelloWorldModule]", WAIT);
    run.wait_for("Start succeeded.", WAIT);
    assert_eq!(run.interrupt(WAIT), Some(0));
}

/// The same module from its pkg under `aimrt_main`, with AimRT's helloworld config.
#[test]
fn helloworld_pkg_runs_under_aimrt_main_until_ctrl_c() {
    let mut run = Running::start(&example_config("helloworld"));
    let (_, line) = run.wait_for("cfg [key1 : val1]", WAIT);
    assert!(line.contains("[HelloWorldModule]"), "{line}");
    run.wait_for("cfg [key2 : val2]", WAIT);
    run.wait_for("Start succeeded.", WAIT);
    assert_eq!(run.interrupt(WAIT), Some(0));
    assert!(run.text().contains("Shutdown succeeded."), "{}", run.text());
}

/// The module registered in code and the one from the config's pkg exchange messages.
fn pair(app: &str, cfg: &str) {
    let mut run = Running::start_program(&binary(app), &["./cfg.yaml"], &example_config(cfg));
    let (_, published) = run.wait_for("Publish new pb event", WAIT);
    let (_, received) = run.wait_for("Receive new pb event", WAIT);
    let data = |l: &str| l.rsplit("data: ").next().unwrap_or_default().to_owned();
    assert_eq!(data(&published), data(&received), "{published}\n{received}");
    assert_eq!(run.interrupt(WAIT), Some(0));
    let text = run.text();
    assert!(text.contains("Shutdown succeeded."), "{text}");
}

#[test]
fn pb_chn_publisher_app_publishes_to_the_subscriber_pkg() {
    pair("pb_chn_publisher_app", "pb_chn_publisher_app");
}

#[test]
fn pb_chn_subscriber_app_receives_from_the_publisher_pkg() {
    pair("pb_chn_subscriber_app", "pb_chn_subscriber_app");
}

#[test]
fn an_app_without_a_config_argument_says_how_to_call_it() {
    let out = Command::new(binary("helloworld_app")).output().unwrap();
    assert_eq!(out.status.code(), Some(255));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("AimRT run with exception and exit. usage: <binary> <cfg_file_path>"),
        "{stdout}"
    );
    let out = Command::new(binary("helloworld_app"))
        .arg("./no_such.yaml")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(255));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("cannot read config file './no_such.yaml'"),
        "{stdout}"
    );
}

/// The module registered in code and the one from the config's pkg call each other (in two
/// libraries), with AimRT's misspelled `timeout_handle_executor` warned about.
fn rpc_pair(app: &str, cfg: &str) {
    let mut run = Running::start_program(&binary(app), &["./cfg.yaml"], &example_config(cfg));
    run.wait_for("did you mean 'timeout_executor'?", WAIT);
    let (_, line) = run.wait_for("Client get rpc ret, status: suc, code 0, msg: OK", WAIT);
    assert!(
        line.ends_with(r#"rsp: {"code":"0","msg":"echo hello world foo, count 1"}"#),
        "{line}"
    );
    assert_eq!(run.interrupt(WAIT), Some(0));
    let text = run.text();
    assert!(
        text.contains(r#"{"aimrt-function_name":"pb:/example_service/GetFooData"}"#),
        "{text}"
    );
}

#[test]
fn normal_pb_rpc_client_app_calls_the_server_pkg() {
    rpc_pair("normal_pb_rpc_client_app", "pb_rpc_client_app");
}

#[test]
fn normal_pb_rpc_server_app_serves_the_client_pkg() {
    rpc_pair("normal_pb_rpc_server_app", "pb_rpc_server_app");
}
