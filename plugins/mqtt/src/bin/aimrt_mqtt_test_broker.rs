//! `aimrt_mqtt_test_broker [ADDRESS] [--tls CERT KEY [--client-ca CA]]`: the small MQTT
//! broker of mqtt_plugin's tests (`aimrt_mqtt::test_broker`), listening on ADDRESS
//! (default `127.0.0.1:1883`, or `127.0.0.1:8883` with `--tls`) until stopped, for trying
//! the mqtt examples without a broker installed. With `--tls` it serves `ssl://` clients
//! with the certificate CERT and its key KEY (PEM), and with `--client-ca` it requires a
//! client certificate signed by a CA of CA. Not for production.

use aimrt_mqtt::test_broker::{Broker, TlsFiles};

const USAGE: &str = "usage: aimrt_mqtt_test_broker [ADDRESS] [--tls CERT KEY [--client-ca CA]]   (default 127.0.0.1:1883, 127.0.0.1:8883 with --tls)";

/// The address and the TLS files of the command line, or what is wrong with it.
fn parse(args: &[String]) -> Result<(Option<String>, Option<TlsFiles>), String> {
    let mut bind = None;
    let mut tls: Option<TlsFiles> = None;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--tls" => {
                let (Some(cert), Some(key)) = (it.next(), it.next()) else {
                    return Err("--tls needs CERT and KEY (PEM files)".into());
                };
                tls.get_or_insert_with(TlsFiles::default).cert = cert.clone();
                tls.get_or_insert_with(TlsFiles::default).key = key.clone();
            }
            "--client-ca" => {
                let Some(ca) = it.next() else {
                    return Err("--client-ca needs CA (a PEM file)".into());
                };
                tls.get_or_insert_with(TlsFiles::default).client_ca = ca.clone();
            }
            other if other.starts_with('-') => return Err(format!("unknown option '{other}'")),
            other if bind.is_none() => bind = Some(other.to_owned()),
            other => return Err(format!("a second address '{other}'")),
        }
    }
    if tls.as_ref().is_some_and(|t| t.cert.is_empty()) {
        return Err("--client-ca needs --tls CERT KEY".into());
    }
    Ok((bind, tls))
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.iter().any(|a| a == "-h" || a == "--help") {
        eprintln!("{USAGE}");
        return;
    }
    let (bind, tls) = match parse(&args) {
        Ok(parsed) => parsed,
        Err(e) => {
            eprintln!("aimrt_mqtt_test_broker: {e}\n{USAGE}");
            std::process::exit(2);
        }
    };
    let default = if tls.is_some() {
        "127.0.0.1:8883"
    } else {
        "127.0.0.1:1883"
    };
    let bind = bind.as_deref().unwrap_or(default);
    let started = match &tls {
        Some(files) => Broker::start_tls(bind, files),
        None => Broker::start(bind),
    };
    match started {
        Ok(broker) => {
            let how = if tls.is_some() { " (TLS)" } else { "" };
            println!("mqtt test broker listening on {}{how}", broker.addr());
            loop {
                std::thread::park();
            }
        }
        Err(e) => {
            eprintln!("aimrt_mqtt_test_broker: cannot serve on {bind}: {e}");
            std::process::exit(1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(line: &str) -> Vec<String> {
        line.split_whitespace().map(str::to_owned).collect()
    }

    #[test]
    fn the_command_line_gives_the_address_and_the_tls_files_or_says_what_is_wrong() {
        let (bind, tls) = parse(&args("127.0.0.1:9 --tls c.pem k.pem --client-ca ca.pem")).unwrap();
        assert_eq!(bind.as_deref(), Some("127.0.0.1:9"));
        let tls = tls.unwrap();
        assert_eq!((tls.cert.as_str(), tls.key.as_str()), ("c.pem", "k.pem"));
        assert_eq!(tls.client_ca, "ca.pem");
        assert_eq!(parse(&args("")).unwrap().0, None);
        assert!(parse(&args("")).unwrap().1.is_none());
        for (line, says) in [
            ("--tls c.pem", "--tls needs CERT and KEY"),
            ("--client-ca ca.pem", "--client-ca needs --tls"),
            ("--client-ca", "--client-ca needs CA"),
            ("--tsl c k", "unknown option '--tsl'"),
            ("a:1 b:2", "a second address 'b:2'"),
        ] {
            let e = parse(&args(line)).unwrap_err();
            assert!(e.contains(says), "{line}: {e}");
        }
    }
}
