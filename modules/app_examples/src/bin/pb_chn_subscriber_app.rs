//! `pb_chn_subscriber_app <cfg>`: AimRT's app-mode subscriber. `NormalSubscriberModule` is
//! registered in code; the config's pkg `libpb_chn_pub_pkg.so` brings the publisher.

fn main() -> std::process::ExitCode {
    app_examples::run_app(vec![Box::new(
        aimrt_channel_examples::NormalSubscriberModule,
    )])
}
