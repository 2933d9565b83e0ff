"""The README's 20-line tour: build a system, run it, retune and swap it live."""

from pb3a import Input, Module, Output, System


class Ticker(Module):
    out = Output(int)
    period = 0.01                      # threaded: step(), then 10 ms asleep
    count = 0                          # public attribute = state

    def step(self):
        self.count += 1
        self.out.write(self.count)


class Scale(Module):
    x = Input(float, policy="queue:64")
    y = Output(float)
    gain = 2.0

    def on_input(self, port):          # event-driven: once per value
        self.y.write(port.read() * self.gain)


class Offset(Scale):                   # same ports and state, another body
    def on_input(self, port):
        self.y.write(port.read() * self.gain + 100)


system = System("quickstart")
system.add("tick", Ticker)
system.add("scale", Scale, state={"gain": 3.0})
system.link("tick.out", "scale.x")
with system.launch() as run:           # one worker process per module
    run.wait(0.5)
    run.set_state("scale", gain=10.0)  # live edit, between two calls
    run.swap("scale", Offset)          # new code, same ports, gain kept
    run.wait(0.5)
    print(run.state("tick"), run.state("scale"))
    print(run.stats().links["tick.out->scale.x"])
