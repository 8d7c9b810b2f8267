# Two commands for a fresh machine: `make demo` and `make test`. Each sets up .venv on first use
# (and again whenever pyproject.toml changes), then runs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench study demo-policy lint format clean firmware-avr

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev,train]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m carrt.demo

test: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) -m bench

# The paper's simulation study, IL against DIRL (about 45 min on 2 cores; results in
# bench/results/dirl_sim/). `$(PY) -m bench.dirl_sim --quick` runs the pipeline in minutes.
study: $(STAMP)
	$(PY) -m bench.dirl_sim

# Reproduce carrt/assets/demo_policy.onnx, the policy `make demo` drives with.
demo-policy: $(STAMP)
	$(PY) training/demo_policy.py

lint: $(STAMP)
	$(PY) -m ruff check --fix .
	$(PY) -m ruff format .

clean:
	rm -rf $(VENV) build firmware_bridge/_build .pytest_cache .hypothesis

# Cross-compile the firmware core for an ATmega328P (Uno/Nano) with the same warnings as the
# host build, plus -Wconversion, to catch 16-bit-int mistakes. Needs avr-gcc
# (Debian/Ubuntu: apt-get install gcc-avr avr-libc).
AVR_SRC := firmware_bridge/firmware/carrt_fw/src
firmware-avr:
	mkdir -p build/avr
	printf '#include "fw_core.h"\nstatic fw_core_t core;\nstatic fw_hal_t hal;\nint main(void) {\n  fw_core_init(&core, &hal, 1u, 0u);\n  for (;;) { fw_core_tick(&core, 0u); }\n}\n' > build/avr/main.c
	avr-gcc -mmcu=atmega328p -std=c99 -Os -Wall -Wextra -Werror -Wshadow -Wconversion -Wsign-conversion \
		-I$(AVR_SRC) build/avr/main.c $(AVR_SRC)/fw_core.c $(AVR_SRC)/fw_frame.c -o build/avr/carrt_core.elf
	avr-size -C --mcu=atmega328p build/avr/carrt_core.elf
