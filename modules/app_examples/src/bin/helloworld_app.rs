//! `helloworld_app <cfg>`: AimRT's hello world in app mode (`HelloWorldModule` registered
//! in code, no pkg).

fn main() -> std::process::ExitCode {
    app_examples::run_app(vec![Box::new(app_examples::HelloWorldModule)])
}
