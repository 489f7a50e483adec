// The admin job page: polls the job's JSON (with the admin session cookie) and shows its
// state, stage and progress live until it ends. URLs come from the page's JSON config.

const POLL_MS = 500;
const FINAL = new Set(['done', 'failed', 'interrupted', 'cancelled']);
const RETRYABLE = new Set(['failed', 'interrupted', 'cancelled']);

export class JobProgress {
  constructor(config, doc = document) {
    this.url = config.job_url;
    this.el = {
      job: doc.getElementById('job'),
      state: doc.getElementById('job-state'),
      stage: doc.getElementById('job-stage'),
      progress: doc.getElementById('job-progress'),
      percent: doc.getElementById('job-percent'),
      error: doc.getElementById('job-error'),
      cancel: doc.getElementById('cancel-form'),
      retry: doc.getElementById('retry-form'),
      object: doc.getElementById('job-object-link'),
      notes: doc.getElementById('job-notes'),
      noteList: doc.getElementById('fit-notes'),
    };
    this.doc = doc;
    this.timer = null;
  }

  start() {
    this.poll();
  }

  async poll() {
    let job;
    try {
      const response = await fetch(this.url, { credentials: 'same-origin',
                                               headers: { Accept: 'application/json' } });
      if (!response.ok) throw new Error(`${response.status} ${response.statusText}`);
      job = await response.json();
    } catch (error) {
      this.el.error.textContent = `Could not read the job's state: ${error.message}; retrying.`;
      this.el.error.hidden = false;
      this.timer = setTimeout(() => this.poll(), POLL_MS * 4);
      return;
    }
    this.show(job);
    if (!FINAL.has(job.state)) this.timer = setTimeout(() => this.poll(), POLL_MS);
  }

  show(job) {
    this.el.job.dataset.state = job.state;
    this.el.state.textContent = job.state;
    this.el.state.className = `state state-${job.state}`;
    this.el.stage.textContent = job.state === 'running' ? job.stage : '';
    this.el.progress.value = job.progress;
    this.el.percent.textContent = `${Math.round(job.progress * 100)}%`;
    this.el.error.textContent = job.error || '';
    this.el.error.hidden = !job.error;
    this.el.cancel.hidden = FINAL.has(job.state);
    this.el.retry.hidden = !RETRYABLE.has(job.state);
    this.el.object.hidden = job.state !== 'done';
    this.showNotes(job.notes || []);
  }

  /** The finished fit's notes (reader warnings, why no atlas...), as the object page lists them. */
  showNotes(notes) {
    if (!this.el.notes) return;
    this.el.noteList.replaceChildren(...notes.map(({ label, text }) => {
      const item = this.doc.createElement('li');
      const strong = this.doc.createElement('strong');
      strong.textContent = label;
      item.append(strong, `: ${text}`);
      return item;
    }));
    this.el.notes.hidden = notes.length === 0;
  }
}

const config = JSON.parse(document.getElementById('admin-config').textContent);
new JobProgress(config).start();
