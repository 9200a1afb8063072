#!/bin/sh
# Makes the TLS test files of the tests and examples of mqtt_plugin and opentelemetry_plugin
# (valid for 100 years; EC P-256 keys, PKCS#8). For trying things only: the private keys are
# in the repository.
#   ca.pem, ca.key        the test CA
#   broker.pem, broker.key  a server's certificate for 127.0.0.1 and localhost, by ca
#   client.pem, client.key  a client certificate, by ca
#   other_ca.pem          a CA that signed none of these (a truststore that must fail)
# Run in this folder: sh make.sh. The files are checked in; the tests never run this.
set -eu
days=36500
key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1"; }
ca() { # name subject
    key "$1.key"
    openssl req -x509 -new -key "$1.key" -sha256 -days $days -subj "/CN=$2" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$1.pem"
}
leaf() { # name subject extensions
    key "$1.key"
    openssl req -new -key "$1.key" -subj "/CN=$2" -out "$1.csr"
    printf '%s\n' "$3" > "$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 -days $days \
        -extfile "$1.ext" -out "$1.pem"
    rm -f "$1.csr" "$1.ext"
}
ca ca "aimrt-rs mqtt test CA"
ca other_ca "aimrt-rs mqtt other CA"
rm -f other_ca.key
leaf broker "aimrt-rs mqtt test broker" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth
subjectAltName=IP:127.0.0.1,DNS:localhost"
leaf client "aimrt-rs mqtt test client" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth
subjectAltName=DNS:aimrt-rs-client"
rm -f ca.srl
# Readable by all, as a clone makes them: mosquitto reads them after dropping root.
chmod 644 ./*.key
