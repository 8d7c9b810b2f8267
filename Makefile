# Two commands for a fresh machine: `make demo` and `make test`. Each first checks the system
# packages it needs (.ci/system-packages: installs the missing ones with apt-get as root or with
# passwordless sudo, or stops with one line naming them), sets up .venv on first use (and again
# whenever pyproject.toml changes), then runs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The car's Python (JetPack 6): the runtime suite also runs under it, in a venv without torch.
PYTHON310 ?= $(firstword $(wildcard $(HOME)/.pyenv/versions/3.10.*/bin/python3.10) python3.10)
VENV310 ?= .venv310
PY310 := $(VENV310)/bin/python
STAMP310 := $(VENV310)/.installed
# LeRobot's own reader, which the tests read carrt's LeRobotDataset export with
# (tests/test_episodes_lerobot_reader.py): a venv of its own, because lerobot-dataset 0.4.4 pins
# older PyAV, OpenCV, numpy and packaging than carrt's; torchvision without its dependencies (its
# wheel is a CUDA build: tests/lerobot_reader.py defines the two operators LeRobot's import asks
# for). Never on the car, never in the 3.10 venv.
LEROBOT_VENV ?= .venv-lerobot
LEROBOT_PY := $(LEROBOT_VENV)/bin/python
LEROBOT_STAMP := $(LEROBOT_VENV)/.installed
# The firmware core is compiled into the package (setup.py); a checkout rebuilds it in place when
# a C file changes, for every venv that uses this tree.
FW_SOURCES := $(wildcard firmware_bridge/firmware/carrt_fw/src/*.[ch] firmware_bridge/firmware/host/*.c) \
	firmware_bridge/core_sources.py setup.py

.PHONY: demo test test-py310 bench study demo-policy il-curve lint format clean firmware emulator core \
	system-demo system-test

# The system packages: `demo` needs gcc, make and a Python with venv and headers; `test` also the
# tests' tools (Xvfb, xdotool, Chromium, the AVR toolchain, simavr, git, Python 3.10). Only checks
# when they are there (a fraction of a second), so it runs every time.
SYSTEM_PACKAGES = PYTHON='$(PYTHON)' PYTHON310='$(PYTHON310)' ARDUINO_AVR='$(ARDUINO_AVR)' \
	SIMAVR_INCLUDE='$(SIMAVR_INCLUDE)' .ci/system-packages
system-demo:
	@$(SYSTEM_PACKAGES) demo
system-test:
	@$(SYSTEM_PACKAGES) test

$(STAMP): pyproject.toml setup.py | system-demo
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip "setuptools>=77"
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[laptop,dev,train]'
	touch $(STAMP)

$(LEROBOT_STAMP): | system-test
	$(PYTHON) -m venv $(LEROBOT_VENV)
	$(LEROBOT_PY) -m pip install --quiet --upgrade pip
	$(LEROBOT_PY) -m pip install --quiet torch==2.13.0
	$(LEROBOT_PY) -m pip install --quiet lerobot-dataset==0.4.4 torchcodec==0.13.0
	$(LEROBOT_PY) -m pip install --quiet --no-deps torchvision==0.28.0
	touch $(LEROBOT_STAMP)

$(STAMP310): pyproject.toml setup.py | system-test
	$(PYTHON310) -m venv $(VENV310)
	$(PY310) -m pip install --quiet --upgrade pip "setuptools>=77"
	$(PY310) -m pip install --quiet -e '.[laptop,dev]'
	touch $(STAMP310)

# Rebuild the in-place firmware core library after a C change (no-op when it is current).
core: $(STAMP)
	$(PY) setup.py --quiet build_ext --inplace
	@if [ -x $(PY310) ]; then $(PY310) setup.py --quiet build_ext --inplace; fi

demo: system-demo $(STAMP) core
	$(PY) -m carrt.demo

# The whole suite under 3.11 (with torch): the runtime tests, the training tests (never in a
# process that ran the simulator: see tests/e2e_rig.py record_sim_dataset), the install tests;
# then the runtime tests under 3.10 (without torch). pytest-xdist runs the runtime tests in
# RUNTIME_JOBS processes (most of their time is a drive in real time, waiting) and the training
# tests in TRAINING_JOBS (torch on one thread each: one per core); the tests marked `alone`
# measure how fast processes stop and run by themselves; the tests marked `realtime` (timings of
# the emulated board and of drives in real time) run REALTIME_JOBS at a time in a pass of their
# own, not beside CPU-heavy tests that starve their emulator. Measured: docs/development.md.
RUNTIME_JOBS ?= 3
REALTIME_JOBS ?= 2
TRAINING_JOBS ?= 2
TRAINING_TESTS = tests/test_train_*.py tests/test_research_train_*.py tests/test_export.py
test: system-test $(STAMP) $(LEROBOT_STAMP) core
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m pytest -q -n $(RUNTIME_JOBS) -m "not install and not realtime" \
		--ignore-glob='tests/test_train_*' --ignore-glob='tests/test_research_train_*' \
		--ignore=tests/test_export.py
	$(PY) -m pytest -q -n $(REALTIME_JOBS) -m realtime
	$(PY) -m pytest -q -n $(TRAINING_JOBS) -m "not alone" $(TRAINING_TESTS)
	$(PY) -m pytest -q -m alone $(TRAINING_TESTS)
	$(PY) -m pytest -q -m install
	$(MAKE) test-py310

test-py310: system-test $(STAMP310) core
	$(PY310) -m pytest -q -n $(RUNTIME_JOBS) --runtime-only -m "not install and not realtime" \
		-p no:cacheprovider
	$(PY310) -m pytest -q -n $(REALTIME_JOBS) --runtime-only -m realtime -p no:cacheprovider

bench: $(STAMP)
	$(PY) -m bench

# The paper's simulation study, IL against DIRL iterations, -unc and IL at each iteration's
# frames, refinement chosen by driving, σ 0, 0.5 and 1.0, 3 seeds each: the settings of the
# runs of 2026-11-25 in research/LOG.md (about 9 hours of them on 2 cores; results in
# research/runs/dirl_sim/, resumable). `$(PY) -m research.dirl_sim --quick` runs every step in
# minutes. The study's claims and their commands: research/README.md.
study: $(STAMP)
	$(PY) -m research.dirl_sim

# Make carrt/assets/demo_policy.onnx again (same recipe, not the same bytes since the simulator
# changed after 2026-11-22), the policy `make demo` drives with (demonstrations,
# imitation, two rounds of expert take-overs each followed by imitation, carrt eval; about
# 56 min on 2 cores).
demo-policy: $(STAMP) core
	$(PY) training/demo_policy.py

# Driving against training data: imitation on 1/4, 1/2 and all of demo-policy's demonstrations,
# and the take-over iteration, judged on the held-out placements (after make demo-policy).
il-curve: $(STAMP) core
	$(PY) -m research.il_curve --work demo-policy-work

lint: $(STAMP)
	$(PY) -m ruff check --fix .
	$(PY) -m ruff format .

clean:
	rm -rf $(VENV) $(VENV310) $(LEROBOT_VENV) build firmware_bridge/_build firmware_bridge/_fw_core*.so \
		.pytest_cache .hypothesis

# The firmware for an ATmega328P (Uno/Nano), built with Debian's Arduino core and avr-gcc (no
# arduino-cli; Debian/Ubuntu: apt-get install gcc-avr avr-libc arduino-core-avr), then its flash
# and RAM use. The core C files are built first on their own with the host build's warnings plus
# -Wconversion, which catches 16-bit-int mistakes. (Debian's avr-gcc 5.4 lacks C++17's DECIMAL_DIG, which
# the core's WString.cpp wants: it gets the compiler's own value.)
ARDUINO_AVR ?= /usr/share/arduino/hardware/arduino/avr
FW_DIR := firmware_bridge/firmware/carrt_fw
AVR_SRC := $(FW_DIR)/src
FW_BUILD := build/firmware
FW_ELF := $(FW_BUILD)/carrt_fw.elf
AVR_FLAGS := -mmcu=atmega328p -DF_CPU=16000000L -DARDUINO=10807 -DARDUINO_AVR_UNO \
	-DARDUINO_ARCH_AVR -Os -g -ffunction-sections -fdata-sections \
	-I$(ARDUINO_AVR)/cores/arduino -I$(ARDUINO_AVR)/variants/standard \
	-I$(ARDUINO_AVR)/libraries/EEPROM/src
AVR_CFLAGS := $(AVR_FLAGS) -std=gnu11
AVR_CXXFLAGS := $(AVR_FLAGS) -std=gnu++11 -fno-exceptions -fno-threadsafe-statics -fpermissive
AVR_CORE_SRC := $(wildcard $(ARDUINO_AVR)/cores/arduino/*.c $(ARDUINO_AVR)/cores/arduino/*.cpp \
	$(ARDUINO_AVR)/cores/arduino/*.S)
AVR_CORE_OBJ := $(patsubst $(ARDUINO_AVR)/cores/arduino/%,$(FW_BUILD)/arduino/%.o,$(AVR_CORE_SRC))
FW_CORE_OBJ := $(FW_BUILD)/src/fw_core.o $(FW_BUILD)/src/fw_frame.o $(FW_BUILD)/src/fw_rc.o
FW_HEADERS := $(wildcard $(AVR_SRC)/*.h)

firmware: $(FW_ELF)
	avr-size -C --mcu=atmega328p $(FW_ELF)

$(FW_ELF): $(FW_BUILD)/carrt_fw.o $(FW_CORE_OBJ) $(FW_BUILD)/arduino.a
	avr-gcc -mmcu=atmega328p -Os -Wl,--gc-sections -o $@ $^ -lm
	avr-objcopy -O ihex -R .eeprom $@ $(FW_BUILD)/carrt_fw.hex

$(FW_BUILD)/carrt_fw.o: $(FW_DIR)/carrt_fw.ino $(FW_HEADERS)
	@mkdir -p $(@D)
	avr-g++ $(AVR_CXXFLAGS) -Wall -Wextra -Werror -x c++ -c $< -o $@

$(FW_BUILD)/src/%.o: $(AVR_SRC)/%.c $(FW_HEADERS)
	@mkdir -p $(@D)
	avr-gcc $(AVR_CFLAGS) -Wall -Wextra -Werror -Wshadow -Wconversion -Wsign-conversion -c $< -o $@

$(FW_BUILD)/arduino.a: $(AVR_CORE_OBJ)
	rm -f $@
	avr-ar rcs $@ $^

$(FW_BUILD)/arduino/%.c.o: $(ARDUINO_AVR)/cores/arduino/%.c
	@mkdir -p $(@D)
	avr-gcc $(AVR_CFLAGS) -w -c $< -o $@

$(FW_BUILD)/arduino/%.cpp.o: $(ARDUINO_AVR)/cores/arduino/%.cpp
	@mkdir -p $(@D)
	avr-g++ $(AVR_CXXFLAGS) -DDECIMAL_DIG=__DECIMAL_DIG__ -w -c $< -o $@

$(FW_BUILD)/arduino/%.S.o: $(ARDUINO_AVR)/cores/arduino/%.S
	@mkdir -p $(@D)
	avr-gcc $(AVR_FLAGS) -x assembler-with-cpp -c $< -o $@

# The emulated board (firmware_bridge/avr_emulator.py builds it on first use): simavr running
# the ELF above, its UART on a pty. Needs simavr and libsimavr-dev.
SIMAVR_INCLUDE ?= /usr/include/simavr
EMULATOR := build/emulator/carrt_avr_emu
emulator: $(EMULATOR)
$(EMULATOR): firmware_bridge/firmware/emulator/carrt_avr_emu.c
	@mkdir -p $(@D)
	gcc -O2 -std=gnu11 -Wall -Wextra -Werror -I$(SIMAVR_INCLUDE) $< -o $@ -lsimavr -lutil
