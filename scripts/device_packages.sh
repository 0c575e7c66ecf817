# Sourced by the device scripts (device_train.sh, device_bench.sh): install the wheels carried in $WHEELS
# (`make device-wheels`) into $SITE when a package the project needs is missing, and put $SITE on
# PYTHONPATH. Needs PYTHON, WHEELS, SITE and the caller's say/die.
install_carried_wheels() {
    if "$PYTHON" -c 'import gymnasium, pettingzoo, highway_env, pygame, google.protobuf' 2>/dev/null; then
        return 0
    fi
    if compgen -G "$WHEELS/*.whl" >/dev/null; then
        say "installing $(ls "$WHEELS"/*.whl | wc -l) wheels from $WHEELS into $SITE"
        "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$SITE" "$WHEELS"/*.whl || die "pip could not install the wheels of $WHEELS"
        export PYTHONPATH="${PYTHONPATH:+$PYTHONPATH:}$SITE"
    else
        say "no wheels in $WHEELS (run \`make device-wheels\` and carry .whl if a package is missing)"
    fi
}
