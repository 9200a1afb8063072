//! `aimrt_mqtt_test_broker [ADDRESS]`: the small MQTT broker of mqtt_plugin's tests
//! (`aimrt_mqtt::test_broker`), listening on ADDRESS (default `127.0.0.1:1883`) until
//! stopped, for trying the mqtt examples without a broker installed. Not for production.

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.iter().any(|a| a == "-h" || a == "--help") || args.len() > 1 {
        eprintln!("usage: aimrt_mqtt_test_broker [ADDRESS]   (default 127.0.0.1:1883)");
        std::process::exit(if args.len() > 1 { 2 } else { 0 });
    }
    let bind = args.first().map_or("127.0.0.1:1883", String::as_str);
    match aimrt_mqtt::test_broker::Broker::start(bind) {
        Ok(broker) => {
            println!("mqtt test broker listening on {}", broker.addr());
            loop {
                std::thread::park();
            }
        }
        Err(e) => {
            eprintln!("aimrt_mqtt_test_broker: cannot listen on {bind}: {e}");
            std::process::exit(1);
        }
    }
}
