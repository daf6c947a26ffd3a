#!/usr/bin/env bash
# Test CA and certificates for quick-stream's TLS + access-control configurations (openssl only).
#
#   deploy/tls/make-certs.sh OUT_DIR [ROUTER_HOST_OR_IP ...]
#
# Writes, for the router and each service, a folder OUT_DIR/NAME/ holding only what that process
# needs: ca.pem, NAME.pem and NAME.key (its own key and no other: point --tls-dir at it, or mount
# its files), signed by a test CA whose certificate is also OUT_DIR/ca.pem. The CA's private key is
# deleted once every certificate is signed: it never sits in a folder a process is given (re-run
# the script to issue new certificates). The certificate's common name (CN) is what the router's access control
# matches: quick-router, quick-capture, quick-flow, quick-motion, quick-render, quick-recorder,
# quick-monitor (read-only: subscribe and liveliness, no publishing). The router's certificate
# carries the given host names / IPs as subjectAltNames (default: localhost 127.0.0.1).
# A test CA is for tests and labs; use your own PKI in production.
set -euo pipefail
out=${1:?usage: make-certs.sh OUT_DIR [ROUTER_HOST_OR_IP ...]}
shift || true
hosts=("$@")
[ ${#hosts[@]} -eq 0 ] && hosts=(localhost 127.0.0.1)
mkdir -p "$out"
out=$(cd "$out" && pwd)
work=$(mktemp -d)  # the CA key and the signing requests: never in OUT_DIR, removed at the end
trap 'rm -rf "$work"' EXIT
cd "$work"
days=825
openssl req -x509 -newkey rsa:2048 -nodes -keyout ca.key -out ca.pem -days "$days" \
  -subj "/CN=quick-stream test CA" -addext "basicConstraints=critical,CA:TRUE" \
  -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
san=""
for h in "${hosts[@]}"; do
  if [[ $h =~ ^[0-9.]+$ ]]; then san+="IP:$h,"; else san+="DNS:$h,"; fi
done
san=${san%,}
make() {  # make NAME CN [SAN]
  local name=$1 cn=$2 alt=${3:-"DNS:$2"}
  openssl req -newkey rsa:2048 -nodes -keyout "$name.key" -out "$name.csr" -subj "/CN=$cn" 2>/dev/null
  printf 'basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' \
    "$alt" > "$name.ext"
  openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$name.pem" -days "$days" \
    -extfile "$name.ext" 2>/dev/null
  rm -f "$name.csr" "$name.ext"
  mkdir -p "$out/$name"
  cp ca.pem "$out/$name/ca.pem"
  mv "$name.pem" "$name.key" "$out/$name/"
  chmod 600 "$out/$name/$name.key"
}
make router quick-router "$san"
for s in capture flow motion render recorder monitor; do
  make "$s" "quick-$s" "DNS:quick-$s,$san"
done
cp ca.pem "$out/ca.pem"
echo "wrote $out: ca.pem and router/, capture/, flow/, motion/, render/, recorder/, monitor/ (each: ca.pem, NAME.pem, NAME.key); the CA key is not kept"
