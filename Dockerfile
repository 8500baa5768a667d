# plccoms in a container: the two binaries on a distroless base (glibc, no
# shell), running as the unprivileged user nonroot (65532).
#
# NOT BUILT BY CI: no container engine runs on this project's machines (the
# docker client is installed, no daemon), so this file has never been built
# here. Build and run it where Docker runs:
#   docker build -t plccoms .
#   docker run --rm -p 127.0.0.1:5010:5010 plccoms    # the demo: a simulated PLC
#   docker compose up -d                              # your configuration (compose.yaml)
#
# The image's configuration is PLCComS.ini.example listening on every
# interface of the container (its loopback is unreachable from outside);
# publish ports to 127.0.0.1 or to the networks that should reach them.
# Logs go to stderr (docker logs), without colour.

FROM rust:1-slim-bookworm AS build
WORKDIR /src
COPY . .
RUN cargo build --release --locked -p plccoms -p plcsim --bins \
    && strip target/release/plccoms target/release/plcsim \
    && mkdir -p /out/etc/plccoms /out/var/lib/plccoms/files \
    && sed 's/^IPADDR_LOCAL  = 127\.0\.0\.1 .*/IPADDR_LOCAL  = 0.0.0.0   # the container'"'"'s interfaces/' \
        PLCComS.ini.example > /out/etc/plccoms/PLCComS.ini \
    && grep -q '^IPADDR_LOCAL  = 0.0.0.0' /out/etc/plccoms/PLCComS.ini

FROM gcr.io/distroless/cc-debian12:nonroot
COPY --from=build /src/target/release/plccoms /src/target/release/plcsim /usr/bin/
COPY --from=build /out/etc/plccoms /etc/plccoms
COPY --from=build --chown=65532:65532 /out/var/lib/plccoms /var/lib/plccoms
WORKDIR /var/lib/plccoms
USER nonroot
EXPOSE 5010
STOPSIGNAL SIGTERM
ENTRYPOINT ["/usr/bin/plccoms"]
CMD ["-c", "/etc/plccoms/PLCComS.ini"]
