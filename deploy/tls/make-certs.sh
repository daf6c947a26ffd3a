#!/usr/bin/env bash
# Test CA and certificates for quick-stream's TLS + access-control configurations (openssl only).
#
#   deploy/tls/make-certs.sh OUT_DIR [ROUTER_HOST_OR_IP ...]
#
# Writes OUT_DIR/ca.pem (+ ca.key) and, for the router and each service, NAME.pem / NAME.key
# signed by that CA. The certificate's common name (CN) is what the router's access control
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
cd "$out"
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
}
make router quick-router "$san"
for s in capture flow motion render recorder monitor; do
  make "$s" "quick-$s" "DNS:quick-$s,$san"
done
chmod 600 ./*.key
echo "wrote $(pwd): ca.pem, router.pem, capture/flow/motion/render/recorder/monitor.pem (+ .key)"
