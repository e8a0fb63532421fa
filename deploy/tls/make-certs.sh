#!/usr/bin/env bash
# Generate a local certificate authority, a router certificate and one client certificate
# per service for framegate's mutual-TLS profile (deploy/secure-router.json5).
#
#   deploy/tls/make-certs.sh DIR [NAME ...]
#
# DIR receives ca.pem/ca.key, router.pem/router.key and NAME.pem/NAME.key for every NAME
# (default: camera gyro mediator detector cli). The certificate's common name is NAME:
# the router's access control grants rights by it, so NAME must be the service name.
# An existing CA in DIR is reused, so certificates for new services can be added later;
# existing certificates are kept unless FORCE=1. A CA whose key is kept elsewhere (offline,
# as it should be) is used with CA_KEY=PATH; DIR/ca.pem without a key is never replaced by a
# new CA (that would silently cut every existing certificate off): the script stops instead.
#
# It also writes ready-to-use Zenoh configs with absolute paths: DIR/router.json5 (from
# deploy/secure-router.json5) and DIR/NAME.json5 (from deploy/secure-client.json5).
#
# Environment: ROUTER_HOSTS (names and addresses clients use to reach the router,
# comma-separated; default localhost,127.0.0.1), DAYS (validity, default 365), FORCE=1,
# CA_KEY (the CA's private key when it is not DIR/ca.key).
# Private keys are created mode 0600. Never commit DIR (deploy/tls/certs/ is git-ignored).
set -euo pipefail

usage() {
    echo "usage: $0 DIR [NAME ...]   (names default to: camera gyro mediator detector cli)" >&2
    exit 2
}
[[ $# -ge 1 ]] || usage
command -v openssl >/dev/null || { echo "error: openssl is not installed" >&2; exit 1; }

out=$1
shift
names=("$@")
[[ ${#names[@]} -gt 0 ]] || names=(camera gyro mediator detector cli)
days=${DAYS:-365}
router_hosts=${ROUTER_HOSTS:-localhost,127.0.0.1}
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
templates=$(cd "$here/.." && pwd)

for name in router "${names[@]}"; do
    # The name becomes a file name, a certificate CN and an ACL subject: keep it plain.
    if [[ ! $name =~ ^[A-Za-z0-9_][A-Za-z0-9_.-]*$ ]]; then
        echo "error: bad name '$name': use letters, digits, '_', '.', '-'" >&2
        exit 2
    fi
done
for name in "${names[@]}"; do
    [[ $name != router && $name != ca ]] || { echo "error: '$name' is reserved" >&2; exit 2; }
done

mkdir -p "$out"
chmod 700 "$out"
out=$(cd "$out" && pwd)
umask 077

new_key() {  # ECDSA P-256 in PKCS#8, which rustls (Zenoh's TLS) reads
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

ca_key=${CA_KEY:-$out/ca.key}
if [[ -n ${CA_KEY:-} ]]; then
    [[ -f $CA_KEY ]] || { echo "error: CA_KEY=$CA_KEY: no such file" >&2; exit 1; }
    [[ -f $out/ca.pem ]] || {
        echo "error: CA_KEY is set but $out/ca.pem is missing: copy the CA certificate there" >&2
        exit 1
    }
    ca_key=$(cd "$(dirname "$CA_KEY")" && pwd)/$(basename "$CA_KEY")
    if [[ $(openssl pkey -in "$ca_key" -pubout 2>/dev/null) != \
          "$(openssl x509 -in "$out/ca.pem" -noout -pubkey 2>/dev/null)" ]]; then
        echo "error: CA_KEY=$CA_KEY is not the key of $out/ca.pem" >&2
        exit 1
    fi
elif [[ -f $out/ca.pem && ! -f $out/ca.key ]]; then
    echo "error: $out/ca.pem exists without ca.key: pass CA_KEY=PATH (the CA's key) to" \
        "issue certificates from it; a new CA would cut off every existing certificate" >&2
    exit 1
elif [[ -f $out/ca.key && ! -f $out/ca.pem ]]; then
    echo "error: $out/ca.key exists without ca.pem: restore ca.pem, or remove ca.key to" \
        "create a new CA" >&2
    exit 1
fi

if [[ ! -f $out/ca.pem ]]; then
    new_key "$out/ca.key"
    openssl req -x509 -new -key "$out/ca.key" -sha256 -days "$days" \
        -subj "/O=framegate/CN=framegate local CA" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$out/ca.pem"
    echo "created CA            $out/ca.pem"
fi

# sign NAME EKU SAN: key + certificate signed by the CA, CN=NAME.
sign() {
    local name=$1 eku=$2 san=$3
    if [[ -f $out/$name.pem && -f $out/$name.key && ${FORCE:-0} != 1 ]]; then
        echo "kept                  $out/$name.pem"
        return
    fi
    new_key "$out/$name.key"
    local ext
    ext=$(mktemp)
    printf '%s\n' \
        "basicConstraints=critical,CA:FALSE" \
        "keyUsage=critical,digitalSignature,keyEncipherment" \
        "extendedKeyUsage=$eku" \
        "subjectAltName=$san" >"$ext"
    openssl req -new -key "$out/$name.key" -subj "/O=framegate/CN=$name" -out "$out/$name.csr"
    openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$ca_key" \
        -CAcreateserial -days "$days" -sha256 -extfile "$ext" -out "$out/$name.pem" 2>/dev/null
    rm -f "$ext" "$out/$name.csr"
    echo "created certificate   $out/$name.pem (CN=$name)"
}

router_san=""
IFS=',' read -ra hosts <<<"$router_hosts"
for host in "${hosts[@]}"; do
    if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then
        router_san+="IP:$host,"
    else
        router_san+="DNS:$host,"
    fi
done
sign router "serverAuth,clientAuth" "${router_san%,}"
for name in "${names[@]}"; do
    sign "$name" clientAuth "DNS:$name"
done
chmod 600 "$out"/*.key
chmod 644 "$out"/*.pem

# Configs with absolute certificate paths, rendered from the templates in deploy/.
render() {  # template destination name
    sed -e "s|deploy/tls/certs/cli\.|deploy/tls/certs/$3.|g" \
        -e "s|deploy/tls/certs/|$out/|g" "$1" >"$2"
    chmod 644 "$2"
}
render "$templates/secure-router.json5" "$out/router.json5" router
for name in "${names[@]}"; do
    render "$templates/secure-client.json5" "$out/$name.json5" "$name"
done
echo "configs               $out/router.json5, $out/<name>.json5"
