//! `pb_chn_publisher_app <cfg>`: AimRT's app-mode publisher. `NormalPublisherModule` is
//! registered in code; the config's pkg `libpb_chn_sub_pkg.so` brings the subscriber.

fn main() -> std::process::ExitCode {
    app_examples::run_app(vec![Box::new(
        aimrt_channel_examples::NormalPublisherModule::default(),
    )])
}
