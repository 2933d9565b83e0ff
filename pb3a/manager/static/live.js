// The websocket feed (/api/live): hello, stats, event, system, state and error messages, with
// reconnection, and the one module whose state this page watches.

export class LiveFeed {
  /** handlers: {hello, stats, event, system, state, error, status(connected: bool)} */
  constructor(handlers) {
    this.handlers = handlers;
    this.watching = null;
    this.socket = null;
    this.retryMs = 500;
    this.closed = false;
  }

  open() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const socket = new WebSocket(`${scheme}://${location.host}/api/live`);
    this.socket = socket;
    socket.onopen = () => {
      this.retryMs = 500;
      this.handlers.status?.(true);
      if (this.watching) this.send({watch: this.watching});
    };
    socket.onmessage = (message) => {
      const data = JSON.parse(message.data);
      this.handlers[data.type]?.(data);
    };
    socket.onclose = () => {
      this.handlers.status?.(false);
      if (this.closed || this.socket !== socket) return;
      // The server restarting or a launch: come back, more slowly each time (5 s at most).
      setTimeout(() => { if (!this.closed) this.open(); }, this.retryMs);
      this.retryMs = Math.min(this.retryMs * 2, 5000);
    };
  }

  /** Ask for `{"type": "state"}` messages about this module (null: none). */
  watch(name) {
    this.watching = name;
    this.send({watch: name});
  }

  send(message) {
    if (this.socket?.readyState === WebSocket.OPEN) this.socket.send(JSON.stringify(message));
  }

  close() {
    this.closed = true;
    this.socket?.close();
  }
}
