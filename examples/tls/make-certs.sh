#!/bin/sh
# Makes the CA and the certificates of a secured cell with openssl (see README, "Securing a
# cell"):
#
#   ./make-certs.sh [DIR] [GATEWAY_HOSTS] [CLIENTS]
#
#   DIR            where the files go (default: tls)
#   GATEWAY_HOSTS  the names and addresses clients use to reach the gateway, space-separated
#                  (default: "localhost 127.0.0.1"); a client checks the gateway's certificate
#                  against the host of its endpoint, so list every one in use
#   CLIENTS        the clients' certificate common names, space-separated (default:
#                  "mes-1 operator-1 dashboard-1"); the cell file's roles name them
#
# It writes ca.pem (give it to every client), gateway.pem and gateway-key.pem (the gateway's),
# and <client>.pem and <client>-key.pem for each client. The CA's key, ca-key.pem, signs
# certificates: keep it off the plant network. Run it again with the same DIR to add clients:
# an existing CA is reused, existing certificates are kept.
set -eu

dir=${1:-tls}
hosts=${2:-"localhost 127.0.0.1"}
clients=${3:-"mes-1 operator-1 dashboard-1"}
days=825

command -v openssl >/dev/null || { echo "make-certs.sh: openssl is not installed" >&2; exit 1; }
mkdir -p "$dir"
cd "$dir"
umask 077 # private keys readable by their owner only

if [ ! -f ca.pem ]; then
    openssl req -x509 -new -nodes -newkey ec -pkeyopt ec_paramgen_curve:P-256 \
        -keyout ca-key.pem -out ca.pem -days 3650 -subj "/CN=cellgate cell CA" 2>/dev/null
    echo "made the CA: $dir/ca.pem (its key, $dir/ca-key.pem, signs certificates: keep it safe)"
fi

# leaf NAME COMMON_NAME [SUBJECT_ALT_NAMES]
leaf() {
    if [ -f "$1.pem" ]; then
        echo "kept $dir/$1.pem"
        return
    fi
    openssl req -new -nodes -newkey ec -pkeyopt ec_paramgen_curve:P-256 \
        -keyout "$1-key.pem" -out "$1.csr" -subj "/CN=$2" 2>/dev/null
    {
        echo "basicConstraints = CA:FALSE"
        echo "keyUsage = digitalSignature"
        echo "extendedKeyUsage = serverAuth, clientAuth"
        if [ -n "${3:-}" ]; then echo "subjectAltName = $3"; fi
    } >"$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial \
        -out "$1.pem" -days "$days" -extfile "$1.ext" 2>/dev/null
    rm -f "$1.csr" "$1.ext"
    echo "made $dir/$1.pem and $dir/$1-key.pem for CN=$2${3:+ ($3)}"
}

san=""
for h in $hosts; do
    case $h in
        *[!0-9.]* | "") entry="DNS:$h" ;; # a name (or an IPv6 address: give it as IP:...)
        *) entry="IP:$h" ;;
    esac
    case $h in IP:* | DNS:*) entry=$h ;; esac
    san="${san:+$san, }$entry"
done
leaf gateway cellgate-gateway "$san"
for c in $clients; do
    leaf "$c" "$c"
done
chmod 644 ca.pem ./*.pem 2>/dev/null || true
chmod 600 ./*-key.pem
